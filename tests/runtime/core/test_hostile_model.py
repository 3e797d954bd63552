"""Model directories and evaluation data under hostile or careless use (issue 27).

Every model here is the bundled one copied into tmp_path and then broken one way; a
broken graph is rewritten with the ``onnx`` package (an independent writer), and its
manifest sha256 updated so that only the property under test is wrong.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.cli import main as cli_main
from geonet_infer.models.manifest import load_manifest

MODEL_DIR = Path(geonet_infer.__file__).resolve().parent / "models" / "small_synth"
SAMPLE = MODEL_DIR.parents[1] / "samples" / "synth_seq"


# ----------------------------------------------------------------------------- helpers
def model_copy(tmp_path: Path) -> Path:
    out = tmp_path / "model"
    shutil.copytree(MODEL_DIR, out)
    return out


def edit_manifest(model: Path, edit) -> None:
    manifest = json.loads((model / "manifest.json").read_text())
    edit(manifest)
    (model / "manifest.json").write_text(json.dumps(manifest))


def rehash(model: Path, file: str) -> None:
    """Record the current sha256 of ``file`` for every manifest entry that points at it."""
    digest = hashlib.sha256((model / file).read_bytes()).hexdigest()

    def edit(manifest):
        for graphs in manifest["graphs"].values():
            for entry in graphs.values():
                if entry["file"] == file:
                    entry["sha256"] = digest

    edit_manifest(model, edit)


def refused(fn, *needles) -> GeoNetError:
    with pytest.raises(GeoNetError) as err:
        fn()
    msg = str(err.value)
    assert "\n" not in msg
    for needle in needles:
        assert str(needle) in msg, (needle, msg)
    return err.value


def frames(n: int = 3) -> list[np.ndarray]:
    files = sorted((SAMPLE / "image").glob("*.png"))[:n]
    return [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]


# ----------------------------------------------------------------------------- 1. size limits
@pytest.mark.parametrize(
    "field, value",
    [("height", 40000), ("width", 40000), ("seq_length", 10**9 + 1), ("height", 100), ("seq_length", 4)],
    ids=["height_40000", "width_40000", "seq_length_1e9", "height_not_multiple", "seq_length_even"],
)
def test_manifest_sizes_outside_the_limits_are_refused_at_load(tmp_path, field, value):
    model = model_copy(tmp_path)
    edit_manifest(model, lambda m: m.update({field: value}))
    refused(lambda: load_manifest(model, verify_files=False), "manifest.json", field, str(value))
    refused(lambda: geonet_infer.load(model), "manifest.json", field)


def test_manifest_size_that_disagrees_with_its_graph_entries_is_refused(tmp_path):
    model = model_copy(tmp_path)
    edit_manifest(model, lambda m: m.update(height=256))  # within the limits, but the graphs take 128
    refused(lambda: geonet_infer.load(model), "manifest.json", "256", "128")


# ----------------------------------------------------------------------------- 2. convention numbers
@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda m: m["conventions"]["image_norm"].update(scale=float("nan")), "image_norm"),
        (lambda m: m["conventions"]["image_norm"].update(offset=float("inf")), "image_norm"),
        (lambda m: m["conventions"]["image_norm"].update(scale=0.0), "image_norm"),
        (lambda m: m["conventions"]["image_norm"].update(offset=1e30), "image_norm"),
        (lambda m: m["conventions"].update(flow_scaling=float("nan")), "flow_scaling"),
        (lambda m: m["conventions"].update(image_norm=[1, 2]), "conventions.image_norm is list"),  # issue 55
    ],
    ids=["norm_nan", "norm_inf", "norm_zero", "norm_huge", "flow_scaling_nan", "norm_list"],
)
def test_nonfinite_or_absurd_convention_numbers_are_refused_at_load(tmp_path, edit, needle):
    model = model_copy(tmp_path)
    edit_manifest(model, edit)
    refused(lambda: geonet_infer.load(model), "manifest.json", needle)


def test_a_manifest_number_of_5001_digits_is_refused_in_one_line(tmp_path):
    """Issue 55: Python's int-string limit raised a ValueError traceback in info and predict."""
    model = model_copy(tmp_path)
    path = model / "manifest.json"
    path.write_text(path.read_text().replace('"height": 128', '"height": ' + "1" * 5001, 1))
    refused(lambda: geonet_infer.load(model), "manifest.json", "cannot parse the manifest", "4300 digits")


# ----------------------------------------------------------------------------- 3. external data
def test_graph_with_external_data_is_refused(tmp_path):
    """posenet.onnx rewritten with its weights in posenet.onnx.data: the manifest's sha256 covers the
    .onnx only, so NaN written into the side file would give NaN poses with exit 0."""
    model = model_copy(tmp_path)
    graph = onnx.load(str(model / "posenet.onnx"))
    onnx.save_model(graph, str(model / "posenet.onnx"), save_as_external_data=True, location="posenet.onnx.data")
    rehash(model, "posenet.onnx")
    data = np.fromfile(model / "posenet.onnx.data", dtype=np.float32)
    data[:] = np.nan
    data.tofile(model / "posenet.onnx.data")
    err = refused(lambda: geonet_infer.load(model), "posenet.onnx", "external data", "posenet.onnx.data", "sha256")
    assert err.path == model / "posenet.onnx"
    refused(lambda: load_manifest(model), "posenet.onnx", "external data")


# ----------------------------------------------------------------------------- 4. paths outside the directory
def test_graph_symlinked_to_outside_the_model_directory_is_refused(tmp_path):
    model = model_copy(tmp_path)
    outside = tmp_path / "elsewhere" / "depthnet.onnx"
    outside.parent.mkdir()
    (model / "depthnet.onnx").rename(outside)  # same bytes: the sha256 still matches
    (model / "depthnet.onnx").symlink_to(outside)
    refused(lambda: geonet_infer.load(model), "depthnet.onnx", "outside the model directory")


def test_symlinked_model_directory_and_links_inside_it_are_fine(tmp_path):
    model = model_copy(tmp_path)
    (model / "posenet.onnx").rename(model / "int8" / "posenet_fp32.onnx")
    (model / "posenet.onnx").symlink_to(Path("int8") / "posenet_fp32.onnx")
    (tmp_path / "link").symlink_to(model)
    assert geonet_infer.load(tmp_path / "link").seq_length == 3


# ----------------------------------------------------------------------------- 5. graph I/O vs the manifest
def _rename_input(model: Path, file: str, old: str, new: str) -> None:
    graph = onnx.load(str(model / file))
    for value in graph.graph.input:
        if value.name == old:
            value.name = new
    for node in graph.graph.node:
        node.input[:] = [new if name == old else name for name in node.input]
    onnx.save_model(graph, str(model / file))
    rehash(model, file)


def _manifest_output_dim(model: Path, graph: str, output: str, axis: int, size: int) -> None:
    """The manifest promises another size than the graph computes (a posenet of 5-frame snippets
    has 4 poses: ORT merges a graph's declared output shape with the inferred one, so the graph
    cannot be made to lie here)."""

    def edit(manifest):
        for spec in manifest["graphs"]["fp32"][graph]["outputs"]:
            if spec["name"] == output:
                spec["shape"][axis] = size

    edit_manifest(model, edit)


def _retype_input(model: Path, file: str, name: str) -> None:
    graph = onnx.load(str(model / file))
    for value in graph.graph.input:
        if value.name == name:
            value.type.tensor_type.elem_type = onnx.TensorProto.DOUBLE
    cast = onnx.helper.make_node("Cast", [name], [name + "_f32"], to=onnx.TensorProto.FLOAT)
    for node in graph.graph.node:
        node.input[:] = [name + "_f32" if i == name else i for i in node.input]
    graph.graph.node.insert(0, cast)
    onnx.save_model(graph, str(model / file))
    rehash(model, file)


@pytest.mark.parametrize(
    "breakage, needles",
    [
        (lambda m: _rename_input(m, "rigidflow.onnx", "target", "tgt"), ("rigidflow.onnx", "target", "tgt")),
        (lambda m: _manifest_output_dim(m, "posenet", "pose", 1, 4), ("posenet.onnx", "'pose'", "['B', 4, 6]")),
        (lambda m: _retype_input(m, "rigidflow.onnx", "pose"), ("rigidflow.onnx", "pose", "float64")),
    ],
    ids=["renamed_input", "output_dim", "input_dtype"],
)
def test_graph_io_that_disagrees_with_the_manifest_is_refused_at_load_and_by_info(tmp_path, capsys, breakage, needles):
    model = model_copy(tmp_path)
    breakage(model)
    err = refused(lambda: geonet_infer.load(model), *needles)
    assert err.path is not None and err.path.name == needles[0]
    assert cli_main(["info", "--model", str(model)]) == 2
    stderr = capsys.readouterr().err.strip()
    assert len(stderr.splitlines()) == 1 and all(str(n) in stderr for n in needles), stderr


# ----------------------------------------------------------------------------- 7. eval pose: NaN in the GT
def _synth_pose_sequence(root: Path, n: int = 6) -> Path:
    seq = root / "seq_0000"
    (seq / "image").mkdir(parents=True)
    for t, rgb in enumerate(frames(n)):
        cv2.imwrite(str(seq / "image" / f"{t:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (seq / "poses.txt").write_text("".join(f"1 0 0 0 0 1 0 0 0 0 1 {t}.0\n" for t in range(n)))
    (seq / "calib.txt").write_text("K: 416 0 208 0 416 64 0 0 1\n")
    return seq


def test_eval_pose_with_nan_in_the_ground_truth_is_an_input_error(tmp_path, capsys):
    seq = _synth_pose_sequence(tmp_path)
    lines = (seq / "poses.txt").read_text().splitlines()
    lines[3] = "1 0 0 0 0 1 0 0 0 0 1 nan"
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    assert cli_main(["eval", "pose", "--data", str(tmp_path), "--method", "identity"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and "poses.txt" in err and "line 4" in err, err
    assert "nan ± nan" not in captured.out


# ----------------------------------------------------------------------------- 8. eval depth: missing GT
def test_eval_depth_with_ground_truth_missing_for_half_the_frames_says_so_and_exits_1(tmp_path, capsys):
    drive = tmp_path / "drive"
    (drive / "image_02" / "data").mkdir(parents=True)
    gt_dir = drive / "proj_depth" / "groundtruth" / "image_02"
    gt_dir.mkdir(parents=True)
    gt = np.zeros((128, 416))
    gt[60:120, 20:400] = 10.0
    for t, rgb in enumerate(frames(6)):
        cv2.imwrite(str(drive / "image_02" / "data" / f"{t:010d}.png"), rgb)
        if t % 2 == 0:
            cv2.imwrite(str(gt_dir / f"{t:010d}.png"), np.round(gt * 256).astype(np.uint16))
    out = tmp_path / "r.json"
    argv = ["eval", "depth", "--data", str(drive), "--method", "constant", "--json", str(out)]
    assert cli_main(argv) == 1
    captured = capsys.readouterr()
    warnings = [line for line in captured.err.splitlines() if "without ground truth" in line]
    assert len(warnings) == 1 and "3 of 6" in warnings[0], captured.err
    data = json.loads(out.read_text())["results"][0]["data"]
    assert data["frames_without_gt"] == ["0000000001", "0000000003", "0000000005"]
    assert json.loads(out.read_text())["results"][0]["metrics"]["count"] == 3
    # asked for explicitly: scored, still named, exit 0
    assert cli_main([*argv, "--allow-missing-gt"]) == 0
    assert "3 of 6" in capsys.readouterr().err
