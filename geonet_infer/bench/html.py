"""``geonet-infer report bench.json``: each case's latency distribution per engine and precision, as one
offline HTML page (issue 59). Reads what ``geonet-infer bench --json`` wrote; rows of an older bench
without raw samples are drawn from their percentiles."""

from __future__ import annotations

import json
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.output.html import Page, require_plotly


def read_bench(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        data["results"], data["environment"]  # noqa: B018
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(
            path, f"not valid JSON, truncated or damaged ({exc.__class__.__name__})", "run bench again"
        ) from None
    except (KeyError, TypeError):
        raise InputError(
            path, "not a `geonet-infer bench --json` file (no results/environment)", "pass the file bench wrote"
        ) from None
    return data


def bench_page(path: Path) -> Page:
    go = require_plotly()
    data = read_bench(path)
    env = data["environment"]
    page = Page(f"geonet-infer bench: {path.name}")
    model = env.get("model") or {}
    page.text(
        f"{env.get('cpu', '?')}; {env.get('usable_cpus', '?')} usable CPUs, {env.get('threads', '?')} threads; "
        f"onnxruntime {env.get('onnxruntime', '?')}; model {model.get('arch', '?')} "
        f"{'(random weights)' if model.get('random_init') else ''}."
    )
    cases = sorted({(r["task"], r["mode"]) for r in data["results"]})
    for task, mode in cases:
        rows = [r for r in data["results"] if (r["task"], r["mode"]) == (task, mode)]
        unit = "per frame" if rows[0].get("unit") == "frame" else "per call"
        page.heading(f"{task}, {mode}: ms {unit}")
        figure = go.Figure()
        for r in rows:
            label = f"{r['backend']} {r['precision']} b{r['batch']}"
            if r.get("samples_ms"):
                figure.add_trace(go.Box(y=r["samples_ms"], name=label, boxpoints="all", jitter=0.4, pointpos=0))
            else:  # an older file: the percentiles it kept
                figure.add_trace(go.Box(name=label, q1=[r["p50_ms"]], median=[r["p50_ms"]], q3=[r["p90_ms"]],
                                        lowerfence=[r["min_ms"]], upperfence=[r["max_ms"]]))  # fmt: skip
        figure.update_layout(yaxis_title="ms", height=360, showlegend=False)
        page.plot(figure)
        page.table(
            ["engine", "precision", "batch", "p50", "p90", "p99", "n"],
            [[r["backend"], r["precision"], r["batch"], *(float(r[k]) for k in ("p50_ms", "p90_ms", "p99_ms")), r["n"]]
             for r in rows],
        )  # fmt: skip
    return page
