"""``python -m benchmarks.model_card`` on tiny inputs (a few seconds).

The model directories here are built with ``onnx.helper``: stand-in graphs with the
exact I/O contract of the exported ones (``export.wrappers.io_spec``), a valid
manifest (``random_init: true``) and, for most of them, an INT8 set; a shifted
stand-in plays the ``--before`` model. A real
``python -m export --random-init`` takes ~35 s even at 64x208, too slow for this
file; the stand-ins make the numbers predictable instead (the "pose network" drives
straight ahead, the "depth network" follows image brightness). The synthetic data is
one 6-frame sequence from ``python -m training.synth`` at 64x208, the real data
2 KITTI frames with Velodyne scans from ``../shared/realdata``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from benchmarks.markdown import sig3
from benchmarks.model_card.cli import main
from benchmarks.model_card.render import render_card
from export.wrappers import io_spec
from geonet_infer import conventions
from geonet_infer.core.predictor import Predictor
from geonet_infer.eval.metrics import depth_floor_share
from geonet_infer.eval.velodyne import velodyne_to_depth_map
from geonet_infer.io import read_image
from geonet_infer.models.manifest import (
    GraphEntry,
    Manifest,
    Provenance,
    Quantization,
    TensorSpec,
    file_sha256,
    load_manifest,
    write_manifest,
)

ROOT = Path(__file__).resolve().parents[2]
H, W = 32, 96  # graph size of the stand-in models
OPSET = 18
STEP = 0.1  # forward motion per frame of the stand-in pose network (relative units)


# ----------------------------------------------------------------------------- stand-in graphs
def _const(name: str, value) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value), name))


def _graph(name: str, seq_length: int, nodes: list) -> onnx.ModelProto:
    spec = io_spec(name, H, W, seq_length)

    def vi(n, s):
        return helper.make_tensor_value_info(n, TensorProto.FLOAT, [d if isinstance(d, int) else "B" for d in s])

    graph = helper.make_graph(nodes, name, [vi(n, s) for n, s in spec.inputs], [vi(n, s) for n, s in spec.outputs])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    onnx.checker.check_model(model)
    return model


def depthnet(seq_length: int, extra: float) -> onnx.ModelProto:
    """disparity = 0.05 + extra + 0.1 * sigmoid(mean over RGB): depth follows brightness."""
    nodes = [
        _const("ax", np.array([1], np.int64)),
        _const("k", np.float32(0.1)),
        _const("c", np.float32(0.05 + extra)),
        helper.make_node("ReduceMean", ["image", "ax"], ["m"], keepdims=1),
        helper.make_node("Sigmoid", ["m"], ["s"]),
        helper.make_node("Mul", ["s", "k"], ["a"]),
        helper.make_node("Add", ["a", "c"], ["disparity"]),
        helper.make_node("Reciprocal", ["disparity"], ["depth"]),
    ]
    return _graph("depthnet", seq_length, nodes)


def posenet(seq_length: int, extra: float) -> onnx.ModelProto:
    """Straight ahead at STEP per frame: target -> source at temporal offset o is t = (0, 0, -STEP * o).

    ``extra`` < 0 imitates a broken INT8 PoseNet (seen on a real export): the vector
    is right but ``pose_matrix`` is the identity (no motion)."""
    k = seq_length // 2
    offsets = [o for o in range(-k, k + 1) if o != 0]  # sources in temporal order
    step = STEP * (1 + extra)
    vec = np.zeros((len(offsets), 6), np.float32)
    mat = np.tile(np.eye(4, dtype=np.float32), (len(offsets), 1, 1))
    for i, o in enumerate(offsets):
        vec[i, 2] = -step * o
        if extra >= 0:
            mat[i, 2, 3] = -step * o
    nodes = [
        _const("ax", np.array([1, 2, 3], np.int64)),
        _const("zero", np.float32(0.0)),
        _const("u3", np.array([1, 2], np.int64)),
        _const("u4", np.array([1, 2, 3], np.int64)),
        _const("vec", vec),
        _const("mat", mat),
        helper.make_node("ReduceMean", ["snippet", "ax"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Unsqueeze", ["z", "u3"], ["z3"]),
        helper.make_node("Unsqueeze", ["z", "u4"], ["z4"]),
        helper.make_node("Add", ["z3", "vec"], ["pose"]),
        helper.make_node("Add", ["z4", "mat"], ["pose_matrix"]),
    ]
    return _graph("posenet", seq_length, nodes)


def rigidflow(seq_length: int, extra: float) -> onnx.ModelProto:
    """rigid flow (0.5, 0) px, warped = source, error = mean |target - source|."""
    nodes = [
        _const("zero", np.float32(0.0)),
        _const("half", np.float32(0.5)),
        _const("ax", np.array([1], np.int64)),
        helper.make_node("Mul", ["depth", "zero"], ["d0"]),
        helper.make_node("Add", ["d0", "half"], ["u"]),
        helper.make_node("Concat", ["u", "d0"], ["rigid_flow"], axis=1),
        helper.make_node("Identity", ["source"], ["warped"]),
        helper.make_node("Sub", ["target", "source"], ["diff"]),
        helper.make_node("Abs", ["diff"], ["ad"]),
        helper.make_node("ReduceMean", ["ad", "ax"], ["error"], keepdims=1),
    ]
    return _graph("rigidflow", seq_length, nodes)


def resflownet(seq_length: int, extra: float) -> onnx.ModelProto:
    """residual = (0.25 + extra) px on both axes; flow = rigid flow (channels 9:11) + residual."""
    nodes = [
        _const("s", np.array([9], np.int64)),
        _const("e", np.array([11], np.int64)),
        _const("ax", np.array([1], np.int64)),
        _const("zero", np.float32(0.0)),
        _const("r", np.float32(0.25 + extra)),
        helper.make_node("Slice", ["flow_input", "s", "e", "ax"], ["rigid"]),
        helper.make_node("Mul", ["rigid", "zero"], ["r0"]),
        helper.make_node("Add", ["r0", "r"], ["residual_flow"]),
        helper.make_node("Add", ["rigid", "residual_flow"], ["flow"]),
    ]
    return _graph("resflownet", seq_length, nodes)


BUILDERS = {"depthnet": depthnet, "posenet": posenet, "rigidflow": rigidflow, "resflownet": resflownet}


def make_model_dir(
    out: Path, seq_length: int = 3, int8: bool = True, int8_static_pose: bool = False, shift: float = 0.0
) -> Path:
    """A model directory the runtime accepts (manifest checked by load_manifest on use).

    ``shift`` is added to the depth head's disparity and to the residual flow: another model
    with the same contract and other numbers (the "before" model)."""
    out.mkdir(parents=True)
    graphs = {"fp32": {}}
    if int8:
        graphs["int8"] = {}
        (out / "int8").mkdir()
    for name, build in BUILDERS.items():
        spec = io_spec(name, H, W, seq_length)
        extra = shift if name in ("depthnet", "resflownet") else 0.0

        def entry(file: str, precision: str, extra: float, build=build, spec=spec) -> GraphEntry:
            onnx.save(build(seq_length, extra), str(out / file))
            return GraphEntry(
                file=file,
                sha256=file_sha256(out / file),
                opset=OPSET,
                precision=precision,
                inputs=tuple(TensorSpec(n, tuple(s)) for n, s in spec.inputs),
                outputs=tuple(TensorSpec(n, tuple(s)) for n, s in spec.outputs),
                exporter="tests/benchmarks/test_model_card.py onnx.helper stand-in",
            )

        graphs["fp32"][name] = entry(f"{name}.onnx", "fp32", extra)
        if int8:
            # The INT8 set's rigidflow is the fp32 file, as in a real export.
            graphs["int8"][name] = (
                graphs["fp32"][name]
                if name == "rigidflow"
                else entry(
                    f"int8/{name}.onnx", "int8", -0.01 if name == "posenet" and int8_static_pose else extra + 0.01
                )
            )
    # arch "small": a real arch, so the manifest declares its disparity head (the runtime checks it).
    manifest = Manifest(
        schema_version=conventions.SCHEMA_VERSION,
        height=H,
        width=W,
        seq_length=seq_length,
        arch="small",
        random_init=True,
        precisions=tuple(graphs),
        graphs=graphs,
        conventions=json.loads(json.dumps(conventions.as_dict())),
        provenance=Provenance(
            architecture="standin", random_init=True, export_date="2000-01-01T00:00:00+00:00", exporter="onnx.helper"
        ),
        metrics={"val_total": 1.5, "best_step": 10},
        quantization=Quantization(
            method="stand-in",
            activation_type="uint8",
            weight_type="int8",
            per_channel=True,
            reduce_range=False,
            calibrate_method="minmax",
            calibration_data="none",
            calibration_samples={"depthnet": 1},
            calibration_intrinsics="none",
            fp32_graphs=("rigidflow",),
            graph_notes={"resflownet": ["fp32 nodes: head_conv"]},
            accuracy_delta={
                "synth_dir": "x",
                "sequences": ["seq_0000"],
                "stride": 2,
                "depth_abs_rel": {"fp32": 0.25, "int8": 0.375, "delta": 0.125},
                "depth_frames": 3,
            },
        )
        if int8
        else None,
    )
    write_manifest(manifest, out)
    return out


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> tuple[Path, Path]:
    """One 6-frame synthetic sequence at 64x208 and a prepared dir whose heldout.txt lists it."""
    root = tmp_path_factory.mktemp("synth")
    synth_dir = root / "synth"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "training.synth",
            "--out",
            str(synth_dir),
            "--sequences",
            "1",
            "--frames",
            "6",
            "--height",
            "64",
            "--width",
            "208",
            "--seed",
            "3",
        ],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    prepared = root / "prepared"
    prepared.mkdir()
    (prepared / "heldout.txt").write_text("".join(f"seq_0000 {i:06d}\n" for i in range(1, 5)))
    return synth_dir, prepared


def _args(model: Path, synth: tuple[Path, Path], kitti: Path, out: Path, *extra: str) -> list[str]:
    return [
        "--model",
        str(model),
        "--synth-dir",
        str(synth[0]),
        "--prepared-dir",
        str(synth[1]),
        "--kitti",
        str(kitti),
        "--out",
        str(out / "models.md"),
        "--json",
        str(out / "card.json"),
        "--kitti-frames",
        "2",
        "--threads",
        "1",
        "--quiet",
        *extra,
    ]


@pytest.fixture(scope="module")
def card3(tmp_path_factory, synth, kitti_raw):
    """The card of a 3-frame stand-in with FP32 and INT8 graphs (INT8 pose matrices without motion),
    with a shifted stand-in (INT8 pose moving) as the ``--before`` model."""
    out = tmp_path_factory.mktemp("card3")
    model = make_model_dir(out / "model", int8_static_pose=True)
    before = make_model_dir(out / "before", shift=0.05)
    assert main(_args(model, synth, kitti_raw, out, "--allow-random-init", "--before", str(before))) == 0
    return (out / "models.md").read_text(), json.loads((out / "card.json").read_text())


def _numbers(obj, where=""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, f"{where}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield where, obj


# ----------------------------------------------------------------------------- tests
def test_card_has_every_table_and_finite_numbers(card3):
    md, result = card3
    assert md.startswith("# Model card")
    assert "```bash\n.venv/bin/python -m benchmarks.model_card --model " in md
    assert "WARNING: RANDOM-INIT MODEL" in md
    kept = "graphs kept in FP32: rigidflow; operator types quantised: every type onnxruntime quantises.\n\n"
    assert kept + "- resflownet: fp32 nodes: head_conv\n" in md
    for heading in (
        "## The model",
        "## Before / after",
        "## Files",
        "## What was measured",
        "## Depth",
        "### Synthetic held-out sequences",
        "### Real KITTI (Velodyne ground truth)",
        "## Optical flow (synthetic held-out sequences)",
        "## Camera pose (synthetic held-out sequences, 5-frame snippets)",
        "## INT8 versus FP32",
        "## Limitations",
    ):
        assert heading in md, heading
    for row in (
        "| model, FP32 |",
        "| model, INT8 |",
        "| constant depth (baseline) |",
        "| zero flow (baseline) |",
        "| DIS medium (baseline) |",
        "| identity pose / no motion (baseline) |",
        "| ORB-VO (baseline) |",
    ):
        assert row in md, row
    assert md.count("| constant depth (baseline) |") == 2  # synthetic and KITTI
    assert "| `depth_abs_rel` | 0.250 | 0.375 | +0.125 |" in md  # the export's own check, from the manifest
    assert "| `val_total` | 1.50 |" in md  # checkpoint metrics from the manifest
    assert "frames 0–1 (2, 1242×375)" in md  # each row names its data
    assert "`synth` held-out (1 seq, 64×208)" in md
    # every graph file with its sha256 prefix
    for f in result["model"]["files"]:
        assert f"`{f['sha256'][:12]}`" in md
    numbers = list(_numbers({k: v for k, v in result.items() if k != "model"}))
    assert numbers and all(math.isfinite(v) for _, v in numbers), [w for w, v in numbers if not math.isfinite(v)]
    syn = result["synthetic"]
    assert syn["depth"]["frames"] == 6 and syn["flow"]["pairs"] == 4 and syn["pose"]["snippets"] == 2
    assert result["kitti"]["frames"] == ["0000000000", "0000000001"]
    assert {r["data"] for r in result["int8_delta"]} == {"synthetic", "kitti"}
    # the KITTI rows scaled by the camera height sit beside the median-scaled ones, failed fits counted
    ch = result["kitti"]["depth"]["camera_height"]
    assert ch["camera_height_m"] == 1.65
    for p in ("fp32", "int8"):
        failed = ch[f"{p}_ground_fit_failed"]
        row = next(
            line for line in md.splitlines() if line.startswith(f"| model, {p.upper()}, scaled by camera height")
        )
        assert "1.65 m (no median scaling)" in row and f"| {2 - len(failed)} of 2" in row
        assert (ch[p] is None) == (len(failed) == 2)
        for f in result["kitti"]["depth"]["per_frame"]:
            assert (f[f"{p}_camera_height"].get("ground_fit") == "failed") == (f["frame"] in failed)
    # the stand-in INT8 differs from FP32 (depth head +0.01, residual flow +0.01 px)
    delta = {(r["data"], r["metric"]): r["delta"] for r in result["int8_delta"]}
    assert delta[("synthetic", "abs_rel")] != 0 and delta[("synthetic", "noc.epe")] != 0


def test_numbers_in_card_come_from_the_run(card3):
    md, result = card3
    d = result["synthetic"]["depth"]
    assert f"| {sig3(d['fp32']['abs_rel'])} | {sig3(d['fp32']['sq_rel'])} |" in md
    f = result["synthetic"]["flow"]["zero_flow_baseline"]
    assert f"| {sig3(f['noc']['epe'])} | {sig3(f['occ']['epe'])} |" in md
    p = result["synthetic"]["pose"]["fp32"]["ate_snippet"]
    assert f"{sig3(p['mean'])} ± {sig3(p['std'])}" in md


def test_card_writes_its_headline_scores_into_the_model_manifest(card3):
    """The measured run puts the card's numbers into the model's manifest (`geonet-infer info` shows
    them); the --before model's manifest is left alone, and the card's directory size counts the new manifest."""
    md, result = card3
    model_dir = Path(result["model"]["dir"])
    written = load_manifest(model_dir).model_card
    k, s = result["kitti"]["depth"], result["synthetic"]
    assert [(x.value, x.baseline_value) for x in written.real] == [
        (k["fp32"]["abs_rel"], k["constant_baseline"]["abs_rel"])
    ]
    assert [(x.value, x.baseline_value) for x in written.synthetic] == [
        (s["depth"]["fp32"]["abs_rel"], s["depth"]["constant_baseline"]["abs_rel"]),
        (s["flow"]["fp32"]["noc"]["epe"], s["flow"]["dis_medium_baseline"]["noc"]["epe"]),
        (s["pose"]["fp32"]["ate_snippet"]["mean"], s["pose"]["orb_vo_baseline"]["ate_snippet"]["mean"]),
    ]
    assert written.synthetic_only is False and "random-init" in written.trained_on  # the stand-in is untrained
    assert load_manifest(result["before"]["model"]["dir"]).model_card is None
    assert result["model"]["dir_bytes"] == sum(f.stat().st_size for f in model_dir.rglob("*") if f.is_file())


def test_depth_floor_is_the_metric_of_the_predictions(card3, kitti_raw):
    """The floor share in the card is depth_floor_share of what the runtime predicts, frame by frame."""
    md, result = card3
    predictor = Predictor(result["model"]["dir"], precision="fp32")
    frames = sorted((kitti_raw / "image_02" / "data").glob("*.png"))[:2]  # the card's --kitti-frames 2
    shares = [depth_floor_share(predictor.depth(read_image(f)).depth) for f in frames]
    assert result["kitti"]["depth"]["fp32"]["floor_share"] == pytest.approx(np.mean(shares), rel=1e-6)
    assert f"model, FP32 {sig3(np.mean(shares))}" in md.split("Depth floor")[1].split("\n")[0]


def _row(md: str, label: str) -> list[str]:
    """The cells of the table row starting with ``label`` (the first such row)."""
    line = next(line for line in md.splitlines() if line.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def _before_after_rows(md: str) -> dict[str, list[str]]:
    """{row label: cells} of the before/after table."""
    section = md.split("## Before / after\n")[1].split("\n## ")[0]
    lines = [line for line in section.splitlines() if line.startswith("| ")][1:]  # not the header
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    return {c[0]: c[1:] for c in cells}


def _headlines(result: dict) -> dict:
    """Per before/after row: (number of one side and precision, baseline, its name, target met?), written
    out here from the JSON blocks, independently of the card's own table."""
    syn, kd = result["synthetic"], result["kitti"]["depth"]
    return {
        "real KITTI frames 0–1 depth AbsRel": (
            lambda side, p: side["kitti"]["depth"][p]["abs_rel"],
            kd["constant_baseline"]["abs_rel"],
            "constant",
            lambda m, b: m < b,
        ),
        "synthetic held-out depth AbsRel": (
            lambda side, p: side["synthetic"]["depth"][p]["abs_rel"],
            syn["depth"]["constant_baseline"]["abs_rel"],
            "constant",
            lambda m, b: m <= 0.15,
        ),
        "synthetic flow EPE-noc (px)": (
            lambda side, p: side["synthetic"]["flow"][p]["noc"]["epe"],
            syn["flow"]["dis_medium_baseline"]["noc"]["epe"],
            "DIS medium",
            lambda m, b: m < b,
        ),
        "synthetic pose ATE (paper ÷N, mean)": (
            lambda side, p: side["synthetic"]["pose"][p]["ate_snippet"]["mean"],
            syn["pose"]["orb_vo_baseline"]["ate_snippet"]["mean"],
            "ORB-VO",
            lambda m, b: m < b,
        ),
    }


def test_classical_baseline_rows(card3):
    """DIS medium and ORB-VO sit in the flow and pose tables beside the trivial baselines, from the run."""
    md, result = card3
    flow, pose = result["synthetic"]["flow"], result["synthetic"]["pose"]
    dis, orb = flow["dis_medium_baseline"], pose["orb_vo_baseline"]
    assert _row(md, "DIS medium (baseline)")[2:] == [
        sig3(dis["noc"]["epe"]),
        sig3(dis["occ"]["epe"]),
        sig3(dis["noc"]["fl"]),
        sig3(dis["occ"]["fl"]),
        "4",
    ]
    assert dis["noc"]["epe"] != flow["zero_flow_baseline"]["noc"]["epe"]  # DIS finds motion
    assert _row(md, "ORB-VO (baseline)")[2:] == [
        f"{sig3(orb['ate_snippet']['mean'])} ± {sig3(orb['ate_snippet']['std'])}",
        f"{sig3(orb['ate_rmse_true']['mean'])} ± {sig3(orb['ate_rmse_true']['std'])}",
        "2",
    ]
    assert orb["pairs"] == 8 and 0 <= orb["failed_pairs"] <= 8
    # no scale fit can make a trajectory worse than no motion (see the card's baselines text)
    assert orb["ate_snippet"]["mean"] <= pose["identity_baseline"]["ate_snippet"]["mean"] + 1e-12
    assert f"{orb['failed_pairs']} of its 8 pairs failed" in md
    limitation = next(line for line in md.splitlines() if line.startswith("* **Flow**"))
    assert "zero flow and OpenCV DIS" in limitation and f"{sig3(dis['noc']['epe'])} px for DIS medium" in limitation


def test_before_after_table_holds_both_runs_numbers(card3, tmp_path):
    md, result = card3
    before = result["before"]
    assert before["model"]["dir"].endswith("before") and result["model"]["dir"].endswith("model")
    # the before model runs the same measurements, without the (model-independent) baselines
    assert set(before["synthetic"]["flow"]) == {"fp32", "int8", "pairs"}
    assert "constant_baseline" not in before["kitti"]["depth"]
    assert before["synthetic"]["pose"]["method"] == result["synthetic"]["pose"]["method"]
    rows = _before_after_rows(md)
    assert list(rows) == list(_headlines(result))
    for label, (number, baseline, name, meets) in _headlines(result).items():
        sides = [number(side, p) for side in (before, result) for p in ("fp32", "int8")]
        assert rows[label][:4] == [sig3(v) for v in sides], label
        assert rows[label][4] == f"{sig3(baseline)} ({name})", label
        assert rows[label][6] == ("yes" if meets(number(result, "fp32"), baseline) else "no"), label
    assert [r[5] for r in rows.values()] == ["below constant", "≤ 0.15", "below DIS medium", "below ORB-VO"]
    # the shifted stand-in differs from the model: a swapped side would show
    assert rows["synthetic held-out depth AbsRel"][0] != rows["synthetic held-out depth AbsRel"][2]
    assert rows["synthetic flow EPE-noc (px)"][0] != rows["synthetic flow EPE-noc (px)"][2]
    assert before["synthetic"]["pose"]["int8"]["static_snippets"] == 0  # after's INT8 pose does not move
    note = md.split("## Before / after\n")[1].split("\n## ")[0].strip().splitlines()[-1]
    assert f"Before: `{before['model']['dir']}`" in note and f"after: `{result['model']['dir']}`" in note
    assert "measured in this one run" in note


@pytest.mark.parametrize(
    ("row", "path", "value", "verdict"),
    [
        ("synthetic held-out depth AbsRel", ("depth", "abs_rel"), lambda dis: 0.15, "yes"),
        ("synthetic held-out depth AbsRel", ("depth", "abs_rel"), lambda dis: 0.1501, "no"),
        ("synthetic flow EPE-noc (px)", ("flow", "noc", "epe"), lambda dis: dis - 0.01, "yes"),
        ("synthetic flow EPE-noc (px)", ("flow", "noc", "epe"), lambda dis: dis, "no"),
    ],
)
def test_meets_target_judges_the_after_fp32_number(card3, row, path, value, verdict):
    """The verdict follows the FP32 number across its threshold (≤ for the depth target, < for a
    baseline); an INT8 number of 0, which would meet every target, does not change it."""
    _, result = card3
    result = json.loads(json.dumps(result))
    task, *keys, key = path
    for precision, number in (
        ("fp32", value(result["synthetic"]["flow"]["dis_medium_baseline"]["noc"]["epe"])),
        ("int8", 0.0),
    ):
        block = result["synthetic"][task][precision]
        for name in keys:
            block = block[name]
        block[key] = number
    assert _before_after_rows(render_card(result))[row][6] == verdict


def test_before_without_int8_shows_na(card3):
    _, result = card3
    result = json.loads(json.dumps(result))
    before = result["before"]
    for block in (*before["synthetic"].values(), before["kitti"]["depth"]):
        block.pop("int8", None)
    for cells in _before_after_rows(render_card(result)).values():
        assert cells[1] == "n/a" and cells[0] != "n/a" and cells[3] != "n/a"


def test_card_renders_a_partly_successful_camera_height_fit(card3):
    """The stand-ins show no road; with one fitted frame injected, the row, count and text follow it."""
    _, result = card3
    result = json.loads(json.dumps(result))
    depth = result["kitti"]["depth"]
    depth["camera_height"]["fp32"] = dict(depth["fp32"], abs_rel=0.123, count=1)
    depth["camera_height"]["fp32_ground_fit_failed"] = ["0000000001"]
    depth["per_frame"][0]["fp32_camera_height"] = dict(depth["per_frame"][0]["fp32"], abs_rel=0.123)
    md = render_card(result)
    row = next(line for line in md.splitlines() if line.startswith("| model, FP32, scaled by camera height"))
    assert "| 0.123 |" in row and row.endswith("| 1 of 2, ground fit failed on 1 |")
    assert "**model, FP32: no ground plane in 1 of 2 frames** (0000000001)" in md
    assert "found a ground plane in 1 of 2 KITTI frames (AbsRel 0.123 on those" in md
    assert "| 0000000000 | " in md and "| 0.123 |" in md.split("Per KITTI frame")[1].splitlines()[4]


def test_kitti_constant_baseline_equals_numpy(card3, kitti_raw):
    """Constant-depth baseline abs_rel = that of the median GT depth as prediction (Garg crop, < 80 m)."""
    _, result = card3
    ours = []
    for stem in ("0000000000", "0000000001"):
        gt = velodyne_to_depth_map(kitti_raw, kitti_raw / "velodyne_points" / "data" / f"{stem}.bin", (375, 1242))
        h, w = gt.shape
        crop = np.zeros_like(gt, dtype=bool)
        crop[int(0.40810811 * h) : int(0.99189189 * h), int(0.03594771 * w) : int(0.96405229 * w)] = True
        g = gt[(gt > 1e-3) & (gt < 80) & crop].astype(np.float64)
        ours.append(np.mean(np.abs(g - np.median(g)) / g))
    per_frame = result["kitti"]["depth"]["per_frame"]
    assert per_frame[0]["constant_baseline"]["abs_rel"] == pytest.approx(ours[0], rel=1e-12)
    assert per_frame[1]["constant_baseline"]["abs_rel"] == pytest.approx(ours[1], rel=1e-12)
    assert result["kitti"]["depth"]["constant_baseline"]["abs_rel"] == pytest.approx(np.mean(ours), rel=1e-12)
    assert result["kitti"]["depth"]["constant_baseline"]["count"] == 2


def test_pose_straight_ahead_model_beats_identity(card3):
    """The stand-in drives straight ahead like the synthetic car: far below the no-motion ATE."""
    md, result = card3
    pose = result["synthetic"]["pose"]
    for key in ("ate_snippet", "ate_rmse_true"):
        assert pose["fp32"][key]["mean"] < 0.2 * pose["identity_baseline"][key]["mean"]
    assert "snippet_from_pose_calls" in pose["method"]
    # The stand-in INT8 PoseNet's matrices carry no motion: flagged, and its ATE is the baseline's.
    assert pose["fp32"]["static_snippets"] == 0 and pose["int8"]["static_snippets"] == 2
    assert pose["int8"]["ate_snippet"] == pose["identity_baseline"]["ate_snippet"]
    assert "**model, INT8: in 2 of 2 snippets the predicted camera does not move at all**" in md


def test_five_frame_model_without_int8(tmp_path, synth, kitti_raw):
    """seq_length 5: PoseNet on each snippet (paper protocol); no INT8 set -> no INT8 rows."""
    model = make_model_dir(tmp_path / "model5", seq_length=5, int8=False)
    assert main(_args(model, synth, kitti_raw, tmp_path, "--allow-random-init")) == 0
    md = (tmp_path / "models.md").read_text()
    result = json.loads((tmp_path / "card.json").read_text())
    assert "| model, INT8 |" not in md and "has no INT8 graphs" in md and result["int8_delta"] == []
    assert "## Before / after" not in md and result["before"] is None  # no --before: no such section
    pose = result["synthetic"]["pose"]
    assert "paper's protocol" in pose["method"]
    assert pose["fp32"]["ate_snippet"]["mean"] < 0.2 * pose["identity_baseline"]["ate_snippet"]["mean"]


def test_random_init_refused_without_flag(tmp_path, synth, kitti_raw, capsys):
    model = make_model_dir(tmp_path / "model")
    assert main(_args(model, synth, kitti_raw, tmp_path)) == 2
    err = capsys.readouterr().err
    assert "random-init" in err and str(model) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "models.md").exists()


@pytest.mark.parametrize("which", ["model", "synth", "prepared", "kitti"])
def test_missing_input_exits_2_naming_the_path(tmp_path, synth, kitti_raw, capsys, which):
    model = tmp_path / "no_such_model"
    paths = {"model": model, "synth": synth[0], "prepared": synth[1], "kitti": kitti_raw}
    if which != "model":
        model = paths["model"] = make_model_dir(tmp_path / "model")
        paths[which] = tmp_path / f"no_such_{which}"
    args = _args(paths["model"], (paths["synth"], paths["prepared"]), paths["kitti"], tmp_path, "--allow-random-init")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert str(paths[which]) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "models.md").exists()


def test_sig3():
    assert [sig3(x) for x in (0.123456, 12.3456, 12345.6, 0.000123456, 9.9951, -1.5, 0.0, 3)] == [
        "0.123",
        "12.3",
        "12300",
        "0.000123",
        "10.0",
        "-1.50",
        "0",
        "3",
    ]


@pytest.mark.parametrize(
    ("flags", "origin"),
    [
        ("--init-checkpoint runs/F/last.pt", "`flow`, initialised from `runs/F/last.pt`"),
        ("--resume runs/G/last.pt", "`flow`, resumed from `runs/G/last.pt`"),
        ("", "`flow` |"),
    ],
)
def test_training_stage_row_says_where_the_run_started(card3, flags, origin):
    _, result = card3
    result = json.loads(json.dumps(result))
    prov = result["model"]["provenance"]
    prov["checkpoint_stage"] = "flow"
    prov["training_command"] = f"python -m training.train --stage flow --out-dir runs/H {flags} --max-steps 9"
    row = next(line for line in render_card(result).splitlines() if line.startswith("| training stage |"))
    assert origin in row


def test_real_section_is_rendered_from_the_eval_all_json(card3, tmp_path, kitti_object):
    """`--real` renders the JSON of `python -m benchmarks.eval_all` (here on the KITTI object frames) as the card's real
    section and its limitation; an eval-all JSON of other graph files is refused."""
    from benchmarks import eval_all
    from benchmarks.model_card.cli import recorded_real
    from geonet_infer.errors import GeoNetError
    from geonet_infer.eval import evaluation

    _, result = card3
    model_dir = Path(result["model"]["dir"])
    root = tmp_path / "realdata"
    root.mkdir()
    (root / "kitti_object_3frames").symlink_to(kitti_object.resolve())
    predictors = {p: Predictor(model_dir, precision=p, threads=1) for p in ("fp32", "int8")}
    real = eval_all.run(
        root, predictors, command="python -m benchmarks.eval_all --data realdata", allow_random_init=True
    )
    evaluation.write_json(tmp_path / "real.json", real)
    (tmp_path / "card.json").write_text(json.dumps(result))
    args = ["--model", str(model_dir), "--from-json", str(tmp_path / "card.json"), "--out", str(tmp_path / "m.md")]
    assert main([*args, "--real", str(tmp_path / "real.json"), "--no-manifest", "--quiet"]) == 0
    md = (tmp_path / "m.md").read_text()
    assert "## Real data: every set in ../shared with ground truth" in md
    assert "Measured by `python -m benchmarks.eval_all --data realdata --json " in md
    (obj,) = real["sets"]
    fp32, int8, const = (obj["results"][k]["metrics"]["abs_rel"] for k in ("fp32", "int8", "constant"))
    assert f"| KITTI object 000000–000002 | AbsRel | 3 | {fp32:.3f} | {int8:.3f} | {const:.3f} |" in md
    v = real["validation"]
    assert v["frames"] == 3 and v["metrics"]["fp32"]["abs_rel"] == pytest.approx(fp32)
    assert (
        f"on the real validation frames (3 frames of other drives and scenes, see Real data) it is {sig3(fp32)}" in md
    )
    assert "**not scored, folder missing**: KITTI raw 2011_09_26 (test drive)" in md  # every absent set is named
    other = make_model_dir(tmp_path / "other", shift=0.05)
    with pytest.raises(GeoNetError, match="other graph files"):
        recorded_real(tmp_path / "real.json", other)


def test_real_pose_experiment_judges_only_snippets_not_trained_on(tmp_path):
    """The rule's pose figure averages the snippets with no trained frame (06 from 31, 01 up to 30 trained),
    worked out by hand on two made-up eval-all results; the card renders the rule and the verdict."""
    from experiments.real_pose_experiment import held_out, render
    from experiments.real_pose_experiment import main as experiment_main

    assert held_out("KITTI odometry 06", "000026") and not held_out("KITTI odometry 06", "000027")
    assert held_out("KITTI odometry 01", "000031") and not held_out("KITTI odometry 01", "000030")
    assert held_out("KITTI odometry 00", "000000")

    def eval_all(ate06: dict, abs_rel: float) -> dict:
        items = [{"name": n, "ate_snippet": v} for n, v in ate06.items()]
        return {
            "command": "python -m benchmarks.eval_all --data realdata",
            "model": {"precisions": ["fp32"]},
            "validation": {"frames": 6, "metrics": {"fp32": {"abs_rel": abs_rel}}},
            "sets": [
                {"task": "pose", "name": "KITTI odometry 06", "role": "", "results": {"fp32": {"items": items}}},
            ],
        }

    # 000000 is held out, 000040 trained on: only the first counts for the rule
    before = eval_all({"000000": 0.04, "000040": 0.04}, 0.30)
    after = eval_all({"000000": 0.03, "000040": 0.01}, 0.30)
    for name, data in (("before", before), ("after", after)):
        (tmp_path / f"{name}.json").write_text(json.dumps(data))
    out = tmp_path / "experiment.json"
    args = ["--before", str(tmp_path / "before.json"), "--after", str(tmp_path / "after.json"), "--out", str(out)]
    assert experiment_main(args) == 0
    e = json.loads(out.read_text())
    assert e["after"]["fp32"]["pose_ate_held_out"] == pytest.approx(0.03)
    assert e["after"]["fp32"]["pose_ate_all"] == pytest.approx(0.02)
    assert e["verdict"] == {"pose_improves": True, "validation_not_worse": True, "ship": True}
    md = "\n".join(render([e]))
    assert "**Shipping rule.** Written before any candidate was scored" in md and "**shipped**" in md
    unscored = {"rule": e["rule"], "train_frames": e["train_frames"], "round": 2}
    two = "\n".join(render([e, unscored]))
    assert two.count("**Shipping rule.**") == 2 and "### Round 1" in two and "### Round 2" in two
    assert two.endswith("Not scored yet.\n")  # a round whose rule is written, its candidate not yet scored
    # worse validation depth: not shipped, however much the pose improves
    (tmp_path / "after.json").write_text(json.dumps(eval_all({"000000": 0.001, "000040": 0.001}, 0.31)))
    assert experiment_main(args) == 0
    assert json.loads(out.read_text())["verdict"]["ship"] is False
