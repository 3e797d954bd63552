"""Memory of a loaded predictor, one fresh process per (model, precision, backend).

``geonet-infer bench`` loads several predictors in one process, and getrusage's peak only
rises, so only its first predictor has a clean figure. Here each configuration runs alone:
RSS before loading, after loading, and the process peak after a short sequence (4 KITTI-size
frames, the e2e path), against the size of the graph files it loaded.

    .venv/bin/python benchmarks/memory.py --model /tmp/geonet_r50 --model small_synth \\
        --json runs/bench/memory.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys
import numpy as np
from geonet_infer import load
from geonet_infer.models.manifest import load_manifest
from geonet_infer.models import resolve_model
from geonet_infer.engines.timing import current_rss_mib, peak_rss_mib

model, precision, backend = sys.argv[1:4]
manifest = load_manifest(resolve_model(model))
graph_mib = manifest.files_mib(precision)
before = current_rss_mib()
predictor = load(model, precision=precision, backend=backend)
loaded = current_rss_mib()
rng = np.random.default_rng(0)
frames = [rng.integers(0, 255, (375, 1242, 3), dtype=np.uint8) for _ in range(4)]
K = np.array([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]])
result = predictor.predict_sequence(frames, camera=K)
peak = peak_rss_mib()
arrays = [v for f in result.frames for v in vars(f).values() if isinstance(v, np.ndarray)]
print(json.dumps({"model": model, "precision": precision, "backend": backend, "graph_files_mib": graph_mib,
                  "rss_before_load_mib": before, "rss_after_load_mib": loaded, "peak_rss_mib": peak,
                  "inputs_mib": sum(f.nbytes for f in frames) / 2**20,
                  "results_mib": sum(a.nbytes for a in arrays) / 2**20,
                  "predictor_mib": peak - before, "predictor_over_graph_files": (peak - before) / graph_mib,
                  "peak_over_graph_files": peak / graph_mib}))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", action="append", required=True, help="bundled name or model directory (repeat)")
    p.add_argument("--precision", default="int8,fp32")
    p.add_argument("--backend", default="onnxruntime,openvino,auto")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    rows = []
    for model in args.model:
        for precision in args.precision.split(","):
            for backend in args.backend.split(","):
                out = subprocess.run(
                    [sys.executable, "-c", CHILD, model, precision, backend], capture_output=True, text=True
                )
                if out.returncode != 0:
                    print(
                        f"memory: {model} {precision} {backend}: {out.stderr.strip().splitlines()[-1]}", file=sys.stderr
                    )
                    continue
                rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
                r = rows[-1]
                print(
                    f"{Path(model).name:<12} {precision:<4} {backend:<11} graphs {r['graph_files_mib']:7.1f} MiB  "
                    f"before {r['rss_before_load_mib']:6.0f}  loaded {r['rss_after_load_mib']:6.0f}  "
                    f"peak {r['peak_rss_mib']:6.0f}  predictor {r['predictor_mib']:6.0f} MiB "
                    f"= {r['predictor_over_graph_files']:.2f}x graphs",
                    flush=True,
                )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
