"""geonet_infer.output.layout: the ONE description of predict's output folder.

What a run writes (on disk), what it lists as its own before writing (its ownership marker), what
summary.json says it wrote and what ``predict --help`` shows are all read off ``LAYOUT``; here
they are checked against each other on a real run with every output switched on.
"""

from __future__ import annotations

import fnmatch
import json

import cv2
import numpy as np

from geonet_infer.cli import main as cli_main
from geonet_infer.output import layout
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES


def test_a_run_writes_exactly_the_files_the_layout_lists(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["predict", str(SAMPLE_FRAMES), "--out", str(out), "--calib", str(SAMPLE_CALIB), "--no-progress"]
    every = ",".join(layout.OUTPUT_NAMES)
    assert cli_main([*args, "--point-cloud", "world", "--point-stride", "16", "--outputs", every]) == 0
    capsys.readouterr()
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} - {layout.OUTPUT_MARKER}
    summary = json.loads((out / layout.SUMMARY_NAME).read_text())
    names = sorted({p.stem for p in (out / "depth").glob("*.npy")})
    assert len(names) == summary["frames"] > 1
    tasks = summary["tasks"]
    expected = layout.run_files(tasks, "world", camera=True, outputs=layout.OUTPUT_NAMES)
    expected |= set().union(*(layout.frame_files(n, tasks, layout.OUTPUT_NAMES, "world") for n in names))
    last = names[-1]  # flow is frame -> next frame: the last frame may get it (listed) but has none
    assert on_disk == expected - {f"flow/{last}.png", f"flow_vis/{last}.png"}
    assert set(summary["written"]["files"]) == set(summary["outputs"])  # each with its bytes
    assert set(json.loads((out / layout.OUTPUT_MARKER).read_text())["files"]) == expected
    patterns = summary["outputs"]
    assert patterns == layout.listed_outputs(tasks, layout.OUTPUT_NAMES, "world", camera=True)
    for rel in on_disk - {layout.SUMMARY_NAME}:  # each file is one of the patterns summary.json gives
        assert any(fnmatch.fnmatchcase(rel, p) for p in patterns), rel
    assert len(patterns) == len(layout.LAYOUT) - 1  # every entry but summary.json is written here


def test_predict_help_lists_every_file_of_the_layout(capsys):
    assert cli_main(["predict", "--help"]) == 0
    text = capsys.readouterr().out
    for entry in layout.LAYOUT:
        assert "  " + entry.path.replace(layout.FRAME, "<frame>") + " " in text, entry.path


def test_the_layout_leaves_out_what_a_run_does_not_make():
    no_vis = layout.chosen_outputs(None, vis=False)
    assert layout.frame_files("f1", ("depth",), no_vis) == {"depth/f1.npy"}
    assert layout.frame_files("f1", ("flow", "pose"), layout.DEFAULT_OUTPUTS) == {"flow/f1.png", "flow_vis/f1.png"}
    assert layout.frame_files("f1", ("depth", "flow"), {"depth-png16"}) == {"depth16/f1.png"}
    assert layout.run_files(("depth",), None, camera=False) == {"summary.json"}
    assert layout.run_files(("pose",), None, camera=False, outputs={"depth-npy"}) == {"summary.json"}
    assert layout.listed_outputs(("pose",), layout.DEFAULT_OUTPUTS, None, camera=False) == [
        "poses_kitti.txt",
        "poses_tum.txt",
    ]


def test_outputs_writes_only_what_is_asked_and_the_16_bit_depth_png_decodes_to_the_depth(tmp_path, capsys):
    out = tmp_path / "out"
    asked = "depth-npy,depth-png16,depth-npy16,poses"
    args = ["predict", str(SAMPLE_FRAMES), "--out", str(out), "--no-progress", "--outputs", asked]
    assert cli_main(args) == 0  # no flow asked: no --calib needed, only depth and pose run
    capsys.readouterr()
    summary = json.loads((out / layout.SUMMARY_NAME).read_text())
    assert summary["tasks"] == ["depth", "pose"]
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert {p.split("/")[0] for p in on_disk} == {
        "depth",
        "depth16",
        "poses_kitti.txt",
        "poses_tum.txt",
        layout.SUMMARY_NAME,
        layout.OUTPUT_MARKER,
    }
    assert not list((out / "depth").glob("*.png"))  # no colour maps: not asked
    names = sorted(p.stem for p in (out / "depth").glob("*.npy"))
    assert len(names) == summary["frames"] == 12
    for name in names:
        depth = np.load(out / "depth" / f"{name}.npy")
        png = cv2.imread(str(out / "depth16" / f"{name}.png"), cv2.IMREAD_UNCHANGED)  # OpenCV, not our reader
        assert png.dtype == np.uint16 and png.shape == depth.shape
        assert 0 < depth.max() < layout.DEPTH_PNG_MAX  # inside the format's range: no clipping here
        assert np.abs(png / 256.0 - depth).max() <= 1 / 512 + 1e-6  # KITTI: round(depth * 256)
        half = np.load(out / "depth16" / f"{name}.npy")
        assert half.dtype == np.float16 and np.allclose(half, depth, rtol=2**-11, atol=0)
    written = summary["written"]
    pngs = sum(p.stat().st_size for p in (out / "depth16").glob("*.png"))
    assert written["files"]["depth16/*.png"] == {"bytes": pngs, "bytes_per_frame": round(pngs / 12)}
    assert written["bytes"] == sum(v["bytes"] for v in written["files"].values())


def test_the_16_bit_depth_png_clips_what_it_cannot_hold(tmp_path):
    from geonet_infer.core.results import FrameResult
    from geonet_infer.output.writer import write_frame

    depth = np.array([[1.0, 300.0], [255.99, 0.5]], np.float32)
    result = FrameResult(
        index=0,
        name="f",
        depth=depth,
        disparity=1 / depth,
        camera_to_world=np.eye(4),
        pose_to_next=None,
        pose_vector_to_next=None,
        flow=None,
        undistorted=False,
        timings_ms={},
    )
    write_frame(tmp_path, result, ("depth",), outputs={"depth-png16"})
    png = cv2.imread(str(tmp_path / "depth16" / "f.png"), cv2.IMREAD_UNCHANGED)
    assert png.tolist() == [[256, 65535], [65533, 128]]  # 300 m: clipped to 65535 / 256 m, said in --help
