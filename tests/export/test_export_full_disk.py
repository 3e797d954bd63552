"""``python -m export`` onto a full disk (issue 55): one line naming the file, exit 3, nothing left behind."""

from __future__ import annotations

import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _small_files_only():  # in the child: no file past 1 MiB (EFBIG), as on a full disk
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2**20, 2**20))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE")
def test_export_onto_a_full_disk_gives_one_line_and_leaves_nothing(tmp_path):
    out = tmp_path / "model"
    argv = [sys.executable, "-m", "export", "--arch", "small", "--random-init", "--out", str(out), "--quiet"]
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=300, preexec_fn=_small_files_only)
    assert proc.returncode == 3, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and ".onnx: File too large" in lines[0], proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # neither the model nor its temporary folder
