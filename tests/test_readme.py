"""The README's "Use it" section runs as written (issue 56): every shell command of its blocks and its
Python block, from a folder with ``../shared`` beside it, as a newcomer would paste them. (Here, not in
tests/runtime/: the whole suite runs it once; the runtime-only run would run it a second time.)

``pip install`` lines are left out (the suite runs in an installed environment). The converter's line
reads ``~/Downloads/geonet_depthnet/model``: HOME points at a temporary folder holding a random-weight
checkpoint of the released depth layout there (``python -m geonet_infer.convert.random_checkpoint``).
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def use_it_blocks() -> list[tuple[str, str]]:
    """(language, code) of each fenced block of the README's "## Use it" section."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Use it") :]
    section = section[: section.index("\n## ", 1)]
    return re.findall(r"```(bash|python)\n(.*?)```", section, flags=re.S)


def shell_commands(code: str) -> list[list[str]]:
    """Each command of a bash block (comments and continuations handled), pip lines left out."""
    joined = code.replace("\\\n", " ")
    commands = []
    for line in joined.splitlines():
        words = shlex.split(line, comments=True)
        if words and words[0] != "pip":
            commands.append(words)
    return commands


def test_the_use_it_section_has_the_commands_a_newcomer_needs():
    blocks = use_it_blocks()
    assert [lang for lang, _ in blocks].count("python") == 1
    firsts = [words[:2] for lang, code in blocks if lang == "bash" for words in shell_commands(code)]
    assert ["geonet-infer", "predict"] in firsts and ["geonet-infer", "convert"] in firsts


@pytest.mark.slow
def test_the_readme_use_it_section_runs_as_written(kitti_raw, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "shared").symlink_to(kitti_raw.parents[1].resolve())  # ../shared/realdata/...
    home = tmp_path / "home"
    subprocess.run(
        [sys.executable, "-m", "geonet_infer.convert.random_checkpoint",
         str(home / "Downloads" / "geonet_depthnet" / "model"), "depth_resnet50", "pose_seq3"],
        check=True, capture_output=True,
    )  # fmt: skip
    env = {**os.environ, "HOME": str(home), "GEONET_INFER_HOME": str(tmp_path / "geonet_home")}
    env["PATH"] = f"{BIN}{os.pathsep}{env['PATH']}"
    for lang, code in use_it_blocks():
        if lang == "python":
            run = subprocess.run([sys.executable, "-c", code], cwd=work, env=env, capture_output=True, text=True)
            assert run.returncode == 0, run.stderr[-2000:]
            assert "(375, 1242) (375, 1242, 2) 5" in run.stdout
            continue
        for words in shell_commands(code):
            words = [str(home / w[2:]) if w.startswith("~/") else w for w in words]  # as a shell expands ~
            run = subprocess.run(words, cwd=work, env=env, capture_output=True, text=True)
            assert run.returncode == 0, f"{shlex.join(words)}: {run.stderr[-2000:]}"
    assert (work / "out" / "kitti" / "poses_kitti.txt").is_file()
    assert (work / "out" / "official" / "summary.json").is_file()
