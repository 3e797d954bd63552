"""geonet_infer.output.layout: the ONE description of predict's output folder.

What a run writes (on disk), what it lists as its own before writing (its ownership marker), what
summary.json says it wrote and what ``predict --help`` shows are all read off ``LAYOUT``; here
they are checked against each other on a real run with every output switched on.
"""

from __future__ import annotations

import fnmatch
import json

from geonet_infer.cli import main as cli_main
from geonet_infer.output import layout
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES


def test_a_run_writes_exactly_the_files_the_layout_lists(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["predict", str(SAMPLE_FRAMES), "--out", str(out), "--calib", str(SAMPLE_CALIB), "--no-progress"]
    assert cli_main([*args, "--point-cloud", "world", "--point-stride", "16"]) == 0
    capsys.readouterr()
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} - {layout.OUTPUT_MARKER}
    summary = json.loads((out / layout.SUMMARY_NAME).read_text())
    names = sorted({p.stem for p in (out / "depth").glob("*.npy")})
    assert len(names) == summary["frames"] > 1
    tasks = summary["tasks"]
    expected = layout.run_files(tasks, "world", camera=True)
    expected |= set().union(*(layout.frame_files(n, tasks, True, "world") for n in names))
    last = names[-1]  # flow is frame -> next frame: the last frame may get it (listed) but has none
    assert on_disk == expected - {f"flow/{last}.png", f"flow_vis/{last}.png"}
    assert set(json.loads((out / layout.OUTPUT_MARKER).read_text())["files"]) == expected
    patterns = summary["outputs"]
    assert patterns == layout.listed_outputs(tasks, True, "world", camera=True)
    for rel in on_disk - {layout.SUMMARY_NAME}:  # each file is one of the patterns summary.json gives
        assert any(fnmatch.fnmatchcase(rel, p) for p in patterns), rel
    assert len(patterns) == len(layout.LAYOUT) - 1  # every entry but summary.json is written here


def test_predict_help_lists_every_file_of_the_layout(capsys):
    assert cli_main(["predict", "--help"]) == 0
    text = capsys.readouterr().out
    for entry in layout.LAYOUT:
        assert "  " + entry.path.replace(layout.FRAME, "<frame>") + " " in text, entry.path


def test_the_layout_leaves_out_what_a_run_does_not_make():
    assert layout.frame_files("f1", ("depth",), vis=False) == {"depth/f1.npy"}
    assert layout.frame_files("f1", ("flow", "pose"), vis=True) == {"flow/f1.png", "flow_vis/f1.png"}
    assert layout.run_files(("depth",), None, camera=False) == {"summary.json"}
    assert layout.listed_outputs(("pose",), True, None, camera=False) == ["poses_kitti.txt", "poses_tum.txt"]
