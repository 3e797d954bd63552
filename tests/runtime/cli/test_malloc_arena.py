"""The CLI puts every thread on glibc's main arena (geonet_infer.cli.one_malloc_arena): counted from
glibc's own report (malloc_stats), with the default settings as the control."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from geonet_infer.cli import _glibc

pytestmark = pytest.mark.skipif(not _glibc(), reason="glibc's malloc only")

# four threads allocate and free at once, then glibc prints one "Arena N:" block per arena on stderr
PROBE = """
import ctypes, sys, threading
from geonet_infer.cli import one_malloc_arena
print(one_malloc_arena())
def churn():
    for _ in range(2000):
        bytearray(4096)
threads = [threading.Thread(target=churn) for _ in range(4)]
for t in threads: t.start()
for t in threads: t.join()
sys.stdout.flush()
ctypes.CDLL(None).malloc_stats()
"""


def _probe(env_extra: dict[str, str], setting: bool) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"} | env_extra
    code = PROBE if setting else PROBE.replace("print(one_malloc_arena())", "print('skipped')")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    arenas = sum(line.startswith("Arena ") for line in done.stderr.splitlines())
    return done.stdout.strip(), arenas


def test_one_arena_for_every_thread():
    said, arenas = _probe({}, setting=True)
    assert said == "True"
    assert arenas == 1


def test_without_it_threads_get_arenas_of_their_own():  # the control: the probe can see more than one
    said, arenas = _probe({}, setting=False)
    assert said == "skipped"
    assert arenas > 1


def test_users_malloc_arena_max_wins():
    said, arenas = _probe({"MALLOC_ARENA_MAX": "3"}, setting=True)
    assert said == "False"
    assert 1 < arenas <= 3
