"""summary.json's latency table adds up to the wall time; the writer threads are shown apart (issue 43, point 4)."""

from __future__ import annotations

import json

import pytest

from geonet_infer.cli import main
from geonet_infer.engines import usable_cpus
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES


@pytest.mark.parametrize("mode", ["latency", "throughput"])
def test_the_stage_table_adds_up_to_the_wall_time_and_states_the_overlap(tmp_path, capsys, mode):
    out = tmp_path / "out"
    argv = ["predict", SAMPLE_FRAMES, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress", "--quiet", "--mode", mode]
    argv += ["--threads", "2"] if mode == "throughput" and usable_cpus() >= 2 else []
    more = ["--camera-height", "1.65", "--video-out", out / "video.mp4", "--point-cloud", "world"]
    assert main([str(a) for a in [*argv, *more, "--point-stride", "8"]]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    table, overlapped = summary["timings_ms_per_frame"], summary["overlapped_ms_per_frame"]
    wall = summary["wall_s"] * 1e3 / summary["frames"]
    # (that the stages plus "untimed" add up to "total" holds by construction: latency_table, tested below)
    assert table["total"] == pytest.approx(wall, rel=1e-9)  # the total is the run's wall time per frame
    assert table["untimed"] >= 0  # the stages are the main thread's, one after another: never more than the wall
    cascade = ("depthnet", "posenet")
    parallel = summary["model"]["workers"] > 1  # throughput mode: the cascade on threads of its own, apart
    stages = (
        "read",
        *(("cascade_wait",) if parallel else cascade),
        "ground_fit",
        "finite_check",
        "colour_scale",
        "video",
        "world_cloud",
        "finish",
    )
    for stage in stages:
        assert table[stage] > 0, stage  # every stage that costs time is in the table
    assert "write" not in table and overlapped["write"] > 0 and overlapped["write_cpu"] > 0
    for stage in cascade if parallel else ():
        assert stage not in table and overlapped[f"workers_{stage}"] > 0
    lines = {line.split()[0]: line for line in printed.splitlines() if line.startswith("  ")}
    assert "overlapped: not in the total" in lines["write"]
    assert "wall time per frame" in lines["total"] and f"{table['total']:.2f}" in lines["total"]


def test_latency_table_on_hand_counted_numbers():
    """10 frames in 2 s: read 1000 ms and depthnet 500 ms in all, the writer thread 300 ms alongside."""
    from geonet_infer.output.latency import latency_table

    sequential, overlapped = latency_table({"read": 1000.0, "depthnet": 500.0, "write": 300.0}, 10, 2.0)
    assert sequential == pytest.approx({"read": 100.0, "depthnet": 50.0, "untimed": 50.0, "total": 200.0})
    assert overlapped == pytest.approx({"write": 30.0})
