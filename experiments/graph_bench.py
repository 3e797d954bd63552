"""One ``geonet-infer bench --modes graph`` run in a subprocess (a fresh process per model: its sessions and
arenas do not carry over), as the experiments time graphs."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path


def bench_graphs_json(
    model: str | Path, tasks: str, precisions: str, backends: str, threads: int, iters: int = 30
) -> dict:
    """The JSON of ``geonet-infer bench --modes graph`` for ``tasks`` x ``precisions`` x ``backends``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.json"
        command = [sys.executable, "-m", "geonet_infer.cli", "bench", "--model", str(model), "--modes", "graph"]
        command += ["--tasks", tasks, "--precision", precisions, "--backend", backends]
        command += ["--threads", str(threads), "--iters", str(iters), "--json", str(out), "--quiet"]
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        return json.loads(out.read_text())
