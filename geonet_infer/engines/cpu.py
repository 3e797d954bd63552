"""What this CPU offers INT8 inference: the x86 features that decide speed and arithmetic (issue 45).

* ``avx2``: the baseline of every x86 server the runtime meets.
* ``avx512f``: wider vectors (AVX-512).
* ``avx512_vnni`` / ``avx_vnni``: VPDPBUSD adds four uint8 x int8 products in int32, exactly.
* ``amx_int8``: AMX tile multiplies (Sapphire Rapids and later), exact as well.

Without VNNI or AMX, INT8 kernels add pairs of products in int16 with saturation
(:func:`int8_kernel` returns "avx2"; ``geonet_infer/convert/int8_arith.py`` emulates the arithmetic).
Read from ``/proc/cpuinfo`` on Linux, checked against numpy's runtime CPU detection (CPUID),
which knows avx2, avx512f and avx512_vnni; where the two disagree (user-mode emulation) and
off Linux, numpy's answer holds and the other flags are None: unknown.
"""

from __future__ import annotations

import platform
from functools import lru_cache
from pathlib import Path

ISA_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")
_NUMPY_NAMES = {"avx2": "AVX2", "avx512f": "AVX512F", "avx512_vnni": "AVX512VNNI"}


def _parse_proc(text: str) -> tuple[str | None, set[str]] | None:
    """(model name, flags) from /proc/cpuinfo text (its first CPU); None if it lists no flags (not x86)."""
    model, flags = None, None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model is None:
            model = value.strip()
        elif key == "flags" and flags is None:
            flags = set(value.split())
    return None if flags is None else (model, flags)


def _from_proc(text: str) -> tuple[str | None, dict[str, bool | None]] | None:
    """(model name, {flag: present}) from /proc/cpuinfo text; None if it lists no flags (not x86)."""
    parsed = _parse_proc(text)
    if parsed is None:
        return None
    model, flags = parsed
    return model, {f: f in flags for f in ISA_FLAGS}


@lru_cache(maxsize=1)
def _proc_cpuinfo() -> str | None:
    try:
        return Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return None


def proc_flags() -> set[str]:
    """Every flag /proc/cpuinfo lists for the first CPU (empty where there is none: not Linux, not x86)."""
    text = _proc_cpuinfo()
    parsed = None if text is None else _parse_proc(text)
    return set() if parsed is None else parsed[1]


def _from_numpy() -> dict[str, bool | None]:
    import importlib

    try:  # numpy >= 2, then 1.x
        features = importlib.import_module("numpy._core._multiarray_umath").__cpu_features__
    except ImportError:  # pragma: no cover
        features = importlib.import_module("numpy.core._multiarray_umath").__cpu_features__
    return {f: bool(features.get(_NUMPY_NAMES[f], False)) if f in _NUMPY_NAMES else None for f in ISA_FLAGS}


@lru_cache(maxsize=1)
def cpu_info() -> dict:
    """``{"model": str | None, "isa": {flag: True/False/None}, "int8_kernel": str, "source": str}``."""
    text = _proc_cpuinfo()
    parsed = None if text is None else _from_proc(text)
    if parsed is not None:
        model, isa = parsed
        source = "/proc/cpuinfo"
        isa, disagree = reconcile(isa, _from_numpy())
        if disagree:
            source = f"CPUID (numpy), as /proc/cpuinfo describes another CPU ({', '.join(disagree)})"
    else:
        model, isa, source = platform.processor() or None, _from_numpy(), "numpy CPU detection"
    return {"model": model, "isa": isa, "int8_kernel": int8_kernel(isa), "source": source}


def reconcile(proc: dict[str, bool | None], cpuid: dict[str, bool | None]) -> tuple[dict[str, bool | None], list[str]]:
    """/proc/cpuinfo's flags checked against the CPUID bits numpy read in this process.

    They differ where the kernel describes another CPU than the one running this code (QEMU's
    user-mode emulation shows the host's flags). Then the CPUID bits hold, the flags numpy cannot
    read become unknown (None), and the flags that differ are returned.
    """
    disagree = [f for f in ISA_FLAGS if cpuid.get(f) is not None and proc.get(f) is not None and cpuid[f] != proc[f]]
    if not disagree:
        return proc, []
    return {f: cpuid.get(f) for f in ISA_FLAGS}, disagree


def int8_kernel(isa: dict[str, bool | None]) -> str:
    """The uint8 x int8 kernel class onnxruntime uses on a CPU with these features:
    "amx_int8", "avx512_vnni", "avx_vnni" (all exact), "avx2" (int16 pairs, saturating), or "none"."""
    for flag in ("amx_int8", "avx512_vnni", "avx_vnni", "avx2"):
        if isa.get(flag):
            return flag
    return "none"


def isa_line(info: dict | None = None) -> str:
    """One line: the features present, then the INT8 arithmetic they give."""
    info = info or cpu_info()
    present = [f for f in ISA_FLAGS if info["isa"].get(f)]
    unknown = [f for f in ISA_FLAGS if info["isa"].get(f) is None]
    arith = {"avx2": "int16 pairs, saturating", "none": "no x86 INT8 kernels"}.get(info["int8_kernel"], "exact")
    line = f"{' '.join(present) or 'none of ' + ', '.join(ISA_FLAGS)} (INT8 kernel {info['int8_kernel']}: {arith})"
    if unknown:
        line += f"; unknown: {', '.join(unknown)}"
    return line
