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


def p50_ms_one_thread(model: str | Path, tasks: str) -> dict[str, float]:
    """p50 ms of ``tasks``' graphs, FP32 and INT8 on onnxruntime and OpenVINO, one thread: {"engine precision": ms}."""
    rows = bench_graphs_json(model, tasks, "fp32,int8", "onnxruntime,openvino", threads=1)["results"]
    return {f"{row['backend']} {row['precision']}": row["p50_ms"] for row in rows}
