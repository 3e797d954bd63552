"""This project's speed milestones (issue 30): the targets one ``geonet-infer bench`` run measures.

They are this repository's goals, not a user's, so they live here and not in the runtime's wheel:
``experiments/speed_targets.py`` reads them off a bench JSON's rows (and adds predict's frames/s and
memory).

    from experiments.speed_milestones import speed_targets
    speed_targets(json.load(open("bench.json"))["results"], "small")
"""

from __future__ import annotations

# The project's speed targets (issue 30) that one bench run measures, batch 1, p50, the e2e ones at
# KITTI size (DEFAULT_INPUT_SIZE): key -> (what, goal, "max" = at most / "min" = at least). 1-4 are
# for the small cascade, 7 for the resnet50 (paper) networks. experiments/speed_targets.py adds
# predict's frames/s and memory, and measures an older revision in the same run.
SPEED_TARGETS: dict[str, tuple[str, float, str]] = {
    "1a_best_engine_ms": ("small cascade, sequence, per frame, e2e 1242x375, best engine (ms)", 8, "max"),
    "1b_onnxruntime_ms": ("same, onnxruntime only (ms)", 12, "max"),
    "2_pre_post_ms": ("pre- and post-processing per frame, e2e - graph (ms)", 1.5, "max"),
    "3_rigid_op_ms": ("rigid-flow op on onnxruntime's host, fastest form (ms)", 1.0, "max"),
    "4_int8_speedup_onnxruntime": ("INT8 cascade vs FP32 on onnxruntime (x faster)", 1.5, "min"),
    "7a_resnet50_int8_depth_ms": ("resnet50, INT8, best engine: DepthNet graph (ms)", 19, "max"),
    "7b_resnet50_int8_flow_pair_ms": ("resnet50, INT8, best engine: flow per pair in a sequence, e2e (ms)", 45, "max"),
}


def target_distance(value: float, goal: float, sense: str) -> float:
    """value / goal for an upper bound, goal / value for a lower one: 1 or less is met."""
    return value / goal if sense == "max" else goal / value


def speed_target_values(results: list[dict], arch: str, kitti_size: bool = True) -> dict[str, float]:
    """This run's value for each target it measured (``results``: bench rows). ``kitti_size``: the
    e2e rows were measured at 1242x375 (otherwise only the graph-only targets are given)."""
    rows = {(r["task"], r["mode"], r["precision"], r["backend"]): r for r in results if r["batch"] == 1}
    engines = sorted({key[3] for key in rows})
    both = ("fp32", "int8")

    def best(task: str, mode: str, precisions: tuple[str, ...], backends: list[str], field: str = "p50_ms"):
        found = [rows[(task, mode, p, b)][field] for p in precisions for b in backends if (task, mode, p, b) in rows]
        return min(found) if found else None

    values: dict[str, float | None] = {}
    if arch == "resnet50":
        values["7a_resnet50_int8_depth_ms"] = best("depth", "graph", ("int8",), engines)
        if kitti_size:
            values["7b_resnet50_int8_flow_pair_ms"] = best("sequence", "e2e", ("int8",), engines, "per_pair_p50_ms")
    else:
        values["3_rigid_op_ms"] = best("rigid_flow", "graph", ("fp32",), ["onnxruntime"])
        if kitti_size:
            values["1a_best_engine_ms"] = best("sequence", "e2e", both, engines)
            values["1b_onnxruntime_ms"] = best("sequence", "e2e", both, ["onnxruntime"])
            pre_post = [
                rows[("sequence", "e2e", p, b)]["p50_ms"] - rows[("sequence", "graph", p, b)]["p50_ms"]
                for p in both
                for b in engines
                if ("sequence", "e2e", p, b) in rows and ("sequence", "graph", p, b) in rows
            ]
            values["2_pre_post_ms"] = min(pre_post) if pre_post else None
            fp32, int8 = (best("sequence", "e2e", (p,), ["onnxruntime"]) for p in both)
            values["4_int8_speedup_onnxruntime"] = fp32 / int8 if fp32 and int8 else None
    return {key: value for key, value in values.items() if value is not None}


def speed_targets(results: list[dict], arch: str, kitti_size: bool = True) -> dict[str, dict]:
    """{key: {what, goal, sense, value, distance}} for each target this run measured (bench --json)."""
    out = {}
    for key, value in speed_target_values(results, arch, kitti_size).items():
        what, goal, sense = SPEED_TARGETS[key]
        out[key] = {
            "what": what,
            "goal": goal,
            "sense": sense,
            "value": value,
            "distance": target_distance(value, goal, sense),
        }
    return out
