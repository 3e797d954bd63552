"""The Markdown of a ``benchmarks/peers.py`` run (its JSON): latency, speed-ups against the GEMM roofline,
accuracy against torch eager, one-off costs, the networks."""

from __future__ import annotations

NETS = ("depthnet", "posenet", "resflownet", "rigidflow")
BACKENDS = ("eager", "compile", "ort_fp32", "ort_int8", "ov_f32", "ov_int8")
LABELS = {
    "eager": "torch eager",
    "compile": "torch.compile",
    "ort_fp32": "ORT fp32",
    "ort_int8": "ORT int8",
    "ov_f32": "OpenVINO f32",
    "ov_int8": "OpenVINO int8",
}


def _fmt(v, digits=1):
    if v is None:
        return "—"
    return f"{v:.{digits}f}" if v >= 10 or digits == 0 else f"{v:.2f}"


def markdown(data: dict) -> str:
    env, roof, res = data["environment"], data["roofline"], data["results"]
    backends = [b for b in data["backends"] if any(r["backend"] == b for r in res)]
    keys = sorted({(r["net"], r["batch"]) for r in res}, key=lambda k: (NETS.index(k[0]), k[1]))
    cell = {(r["net"], r["batch"], r["backend"]): r for r in res}
    m = env["model"]
    lines = [
        f"# GeoNet peers: {m['arch']} {m['height']}x{m['width']}"
        + (f" (random weights, seed {m['seed']})" if m["random_init"] else f" ({m['checkpoint']})"),
        "",
        f"- CPU: {env['cpu']}, {env['usable_cpus']} usable CPUs, flags {' '.join(env['cpu_flags'])}; "
        f"{env['threads']} threads per engine",
        f"- Python {env['python']}, torch {env['torch']} ({env.get('torch_cpu_capability')}), onnxruntime "
        f"{env['onnxruntime']}, openvino {env['openvino']}, numpy {env['numpy']}",
        f"- one interleaved run: {env['method']['warmup']} warm-up, {env['method']['rounds']} rounds x "
        f"{env['method']['block']} calls per engine (rotating order, quiet-wait, >= "
        f"{env['method']['rewarm_ms']:g} ms re-warm), GC off; wall {env['wall_s']} s; load average "
        f"{env['load_average_start']} -> {env['load_average_end']}"
        + (f"; **{env['busy_warning']}**" if env.get("busy_warning") else ""),
        f"- graphs: {m['onnx_dir']}",
        "",
        f"## Roofline (GEMM n = {roof['n']})",
        "",
        "| kernel | best | median |",
        "|---|---|---|",
    ]
    for k in ("numpy_sgemm_fp32_gflops", "torch_sgemm_fp32_gflops", "torch_int_mm_s8s8s32_gops"):
        if f"{k}_best" in roof:
            lines.append(f"| {k} | {roof[k + '_best']:.1f} | {roof[k + '_median']:.1f} |")

    def backend_table(title: str, fmt) -> list[str]:
        out = [
            "",
            title,
            "",
            "| net | B | " + " | ".join(LABELS[b] for b in backends) + " |",
            "|---|---|" + "---|" * len(backends),
        ]
        for net, batch in keys:
            row = [fmt(cell[(net, batch, b)]) if (net, batch, b) in cell else "—" for b in backends]
            out.append(f"| {net} | {batch} | " + " | ".join(row) + " |")
        return out

    def latency(r) -> str:
        g = f" ({r['gflops_at_p50']:.0f})" if r["gflops_at_p50"] else ""
        return f"{_fmt(r['p50_ms'])} / {_fmt(r['p90_ms'])}{g}"

    def speedup(r) -> str:
        sp = f"{r['speedup_vs_ort_fp32']:.2f}×" if r["speedup_vs_ort_fp32"] else "—"
        return sp + (f", {100 * r['roofline_fraction']:.0f} %" if r["roofline_fraction"] else "")

    lines += backend_table("## Latency, ms p50 / p90 (GFLOP/s at p50)", latency)
    lines += backend_table(
        "## Speedup vs ORT fp32 (p50) and fraction of the GEMM roofline "
        "(fp32 engines vs torch sgemm, int8 vs torch._int_mm)",
        speedup,
    )
    lines += [
        "",
        "## max |Δ| vs torch eager, per output",
        "",
        "| net | B | max\\|ref\\| | " + " | ".join(LABELS[b] for b in backends if b != "eager") + " |",
        "|---|---|---|" + "---|" * len([b for b in backends if b != "eager"]),
    ]
    for net, batch in keys:
        ref = next((r for r in res if r["net"] == net and r["batch"] == batch), None)
        row = []
        for b in backends:
            if b == "eager":
                continue
            r = cell.get((net, batch, b))
            row.append("—" if r is None else ", ".join(f"{d:.1e}" for d in r["max_abs_diff_vs_eager"]))
        lines.append(
            f"| {net} | {batch} | {', '.join(f'{v:.3g}' for v in ref['ref_max_abs'])} | " + " | ".join(row) + " |"
        )
    lines += [
        "",
        "## One-off costs (setup s / first call ms)",
        "",
        "| net | B | " + " | ".join(LABELS[b] for b in backends) + " |",
        "|---|---|" + "---|" * len(backends),
    ]
    for net, batch in keys:
        row = []
        for b in backends:
            r = cell.get((net, batch, b))
            row.append("—" if r is None else f"{r['setup_s']:.1f} / {r['first_call_ms']:.0f}")
        lines.append(f"| {net} | {batch} | " + " | ".join(row) + " |")
    lines += [
        "",
        "## Networks",
        "",
        "| net | params (M) | conv GMACs @b1 | ONNX MiB (fp32 / int8) |",
        "|---|---|---|---|",
    ]
    for net, info in data["nets"].items():
        gm = info.get("conv_gmacs", {})
        b1 = gm.get(1, gm.get("1"))
        lines.append(
            f"| {net} | {info['params_m']:.3f} | {b1:.3f} | " if b1 else f"| {net} | {info['params_m']:.3f} | n/a | "
        )
        lines[-1] += " / ".join(str(v) for v in info["onnx_mib"].values()) + " |"
    if data["failures"]:
        lines += ["", "## Failures", ""]
        lines += [f"- {f['net']} b{f['batch']} {LABELS[f['backend']]}: {f['error']}" for f in data["failures"]]
    return "\n".join(lines) + "\n"
