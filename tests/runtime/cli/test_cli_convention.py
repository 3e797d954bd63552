"""One CLI convention: every command line of the repository exits 2 with one line naming the bad item.

Each CLI runs as a user would start it (``python -m ...`` in a fresh process), so the test also
covers the ``__main__`` wiring: no traceback, no progress bar, no usage text before the message.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
MISSING = "no_such_input"  # a path under tmp_path that is never created

# (module, argv with {missing} / {out} / {file} placeholders, the item the message must name)
CASES = [
    ("training.prepare", ["--kind", "synth", "--src", "{missing}", "--out", "{out}"], "{missing}"),
    ("training.synth", ["--out", "{file}/sub", "--sequences", "1", "--frames", "2"], "{file}"),
    ("training.train", ["--data-dir", "{missing}", "--out-dir", "{out}", "--max-steps", "1"], "{missing}"),
    ("training.evaluate", ["--checkpoint", "{missing}", "--data", "{missing}"], "{missing}"),
    (
        "benchmarks.model_card",
        [
            "--model",
            "{missing}",
            "--synth-dir",
            "{missing}",
            "--prepared-dir",
            "{missing}",
            "--kitti",
            "{missing}",
            "--out",
            "{out}.md",
        ],
        "{missing}",
    ),
    ("training.summary", ["--height", "0"], "--height"),
    ("training.stereo_val", ["--realdata", "{missing}", "--out", "{out}"], "{missing}"),
    ("training.photometric", ["--checkpoint", "{missing}", "--data-dir", "{out}"], "{missing}"),
    (
        "training.checkpoint",
        ["--interpolate", "{missing}", "{missing}", "0.5", "{out}.pt"],
        "{missing}",
    ),  # no input path: the bad size is the item
    ("export", ["--checkpoint", "{missing}", "--out", "{out}"], "{missing}"),
    ("geonet_infer.cli", ["predict", "{missing}", "--out", "{out}"], "{missing}"),
    ("geonet_infer.cli", ["batch", "{missing}", "--out", "{out}"], "{missing}"),
    ("geonet_infer.cli", ["bench", "--model", "{missing}"], "{missing}"),
    ("geonet_infer.cli", ["info", "--model", "{missing}"], "{missing}"),
    ("geonet_infer.cli", ["demo", "--model", "{missing}", "--out", "{out}"], "{missing}"),
    ("geonet_infer.cli", ["eval", "depth", "--data", "{missing}"], "{missing}"),
]


def _id(case) -> str:
    module, argv, _ = case
    return module if module != "geonet_infer.cli" else f"geonet-infer {argv[0]}"


@pytest.mark.train_extra
@pytest.mark.parametrize("case", CASES, ids=[_id(c) for c in CASES])
def test_bad_input_exits_2_with_one_line_naming_it(case, tmp_path):
    if not case[0].startswith("geonet_infer") and importlib.util.find_spec("torch") is None:
        pytest.skip("training and export need the train extra (torch)")
    module, argv, item = case
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    paths = {"missing": str(tmp_path / MISSING), "out": str(tmp_path / "out"), "file": str(a_file)}
    argv = [a.format(**paths) for a in argv]
    run = subprocess.run(
        [sys.executable, "-m", module, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
        timeout=300,
    )
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr
    assert len(lines) == 1, run.stderr
    assert item.format(**paths) in lines[0]
    assert "error" in lines[0]
    assert not (tmp_path / MISSING).exists()
