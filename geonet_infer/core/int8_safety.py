"""Whether an INT8 graph computes exactly on this CPU with a given engine (issue 45).

Without VNNI or AMX (:func:`geonet_infer.engines.cpu.int8_kernel` "avx2"), uint8 x int8 kernels add
pairs of products in int16 with saturation: 8-bit weights beyond +-64 overflow
(``geonet_infer/convert/int8_arith.py``). The manifest records, per INT8 graph, whether its weights stay
within that bound (``quantization.int8_kernels``, written by export).
"""

from __future__ import annotations

from geonet_infer.engines.cpu import cpu_info


def int8_unsafe_reason(engine: str, kernels: dict | None, kernel: str | None = None) -> str | None:
    """Why this engine's INT8 result for a graph with the recorded ``kernels`` is not exact on a CPU
    whose INT8 kernel is ``kernel`` (default: this CPU's), or None when it is."""
    kernel = kernel or cpu_info()["int8_kernel"]
    if kernel != "avx2":
        return None  # VNNI/AMX sum in int32 exactly; non-x86 CPUs have no such kernels
    if engine == "onnxruntime":
        return None  # the runtime's sessions set session.x64quantprecision: exact U8U8 kernels
    if kernels and kernels.get("avx2_u8s8"):
        return None  # every weight within +-64: no pair can overflow
    recorded = "has int8 weights beyond +-64" if kernels else "does not record its int8 weight range"
    return f"{engine} INT8 without VNNI adds products in saturating int16 pairs and the manifest {recorded}"
