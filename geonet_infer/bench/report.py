"""The rows and tables ``geonet-infer bench`` reports: one JSON row per timed case, the text table
and the paper's "per example" line."""

from __future__ import annotations

from geonet_infer.engines.timing import Case


def result_row(task: str, mode: str, precision: str, backend: str, batch: int, case: Case, extra: dict) -> dict:
    stats = case.stats()
    if task == "sequence":
        per_frame = stats.scaled(1.0 / extra["frames"])
        row = per_frame.as_dict()
        row["per_pair_p50_ms"] = stats.p50_ms / extra["pairs"]
        row["per_item_p50_ms"] = per_frame.p50_ms
    else:
        row = stats.as_dict()
        row["per_item_p50_ms"] = stats.p50_ms / batch
    row["first_call_ms"] = case.first_call_ms
    # every timed call in ms, in the unit of the row (per frame for sequence): `geonet-infer report` draws them
    per_unit = 1.0 / extra["frames"] if task == "sequence" else 1.0
    row["samples_ms"] = [round(ns / 1e6 * per_unit, 4) for ns in case.samples_ns]
    return {"task": task, "mode": mode, "precision": precision, "backend": backend, "batch": batch, **row, **extra}


def format_table(results: list[dict]) -> str:
    head = (
        f"{'task':<11} {'mode':<5} {'prec':<4} {'backend':<11} {'batch':>5} {'p50 ms':>9} {'p90 ms':>9} "
        f"{'p99 ms':>9} {'mean +- std ms':>17} {'ms/item':>9} {'items/s':>8}"
    )
    lines = [head, "-" * len(head)]
    for r in results:
        unit = "/frame" if r["unit"] == "frame" else ""
        lines.append(
            f"{r['task']:<11} {r['mode']:<5} {r['precision']:<4} {r['backend']:<11} {r['batch']:>5} "
            f"{r['p50_ms']:>9.2f} {r['p90_ms']:>9.2f} {r['p99_ms']:>9.2f} "
            f"{r['mean_ms']:>8.2f} +- {r['std_ms']:<6.2f} {r['per_item_p50_ms']:>9.2f} {r['fps']:>8.1f}"
            + (f"  ({unit})" if unit else "")
        )
    return "\n".join(lines)


def paper_line(results: list[dict], precision: str, backend: str) -> str | None:
    """'per example' like the paper (batch 1, p50): depth, flow per pair in a sequence, pose."""
    pick = {
        (r["task"], r["mode"]): r
        for r in results
        if r["precision"] == precision and r["backend"] == backend and r["batch"] == 1
    }
    parts = []
    for label, key, field in (
        ("depth", ("depth", "e2e"), "p50_ms"),
        ("flow/pair (sequence)", ("sequence", "e2e"), "per_pair_p50_ms"),
        ("flow (one pair)", ("flow", "e2e"), "p50_ms"),
        ("pose", ("pose", "e2e"), "p50_ms"),
    ):
        if key in pick:
            parts.append(f"{label} {pick[key][field]:.1f} ms")
    return f"per example, {precision}, {backend}, batch 1, e2e p50: " + ", ".join(parts) if parts else None
