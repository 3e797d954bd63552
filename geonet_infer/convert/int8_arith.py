"""The integer arithmetic of onnxruntime's x86 INT8 kernels, emulated in numpy (issue 45).

An INT8 graph (QDQ, uint8 activations, int8 weights: :mod:`geonet_infer.convert.quantize`) runs its
convolutions as uint8 x int8 dot products. How they are summed depends on the CPU:

* VNNI (``avx512_vnni``, ``avx_vnni``) and AMX (``amx_int8``): VPDPBUSD / TDPBUSD add four
  products straight into int32: exact (:func:`dot_exact`).
* AVX2 only (AMD EPYC Zen 2/3, Intel before Cascade Lake; also AVX-512 without VNNI):
  VPMADDUBSW adds *pairs* of products into int16 **with saturation**, then VPMADDWD with ones
  widens the pairs to int32 (:func:`dot_avx2_u8s8`). Two products of 255 x 127 give 64770,
  stored as 32767: weights beyond +-64 can overflow.

onnxruntime's remedy on such CPUs, session option ``session.x64quantprecision`` (which the
runtime sets: :data:`geonet_infer.engines.onnxruntime.X64_QUANT_PRECISION`), stores an int8
weight tensor holding any value outside [-64, 64] as uint8 (w + 128) and runs it with U8U8
kernels, which widen to int16 before multiplying: exact. :func:`dot_as_onnxruntime_runs_it`
puts both together. Checked against onnxruntime's real AVX2 kernels under
``qemu-x86_64 -cpu Haswell`` (docs/performance.md, "AVX2-only CPUs").
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper

INT16_MIN, INT16_MAX = -32768, 32767
# An int8 weight within this bound cannot overflow a VPMADDUBSW pair: 2 x 255 x 64 = 32640 <= 32767.
# The same bound decides onnxruntime's remedy (onnxruntime/core/optimizer/qdq_transformer/s8_to_u8.h).
AVX2_SAFE_WEIGHT = 64


def dot_exact(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """uint8 (M, K) x int8 (K, N) -> int32 (M, N), summed exactly (VNNI, AMX, U8U8 kernels)."""
    return a.astype(np.int64) @ w.astype(np.int64)


def dot_avx2_u8s8(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """uint8 (M, K) x int8 (K, N) -> int32 (M, N) as AVX2 U8S8 kernels compute it.

    VPMADDUBSW multiplies each uint8 of ``a`` with the int8 of ``w`` at the same k and adds
    adjacent pairs (k = 0+1, 2+3, ...) into int16 with signed saturation; VPMADDWD with a
    vector of ones then adds those int16 pairs into int32 (exact from there on). K is padded
    with zeros to even length, as the kernels pad it.
    """
    a = np.asarray(a, np.uint8)
    w = np.asarray(w, np.int8)
    if a.shape[1] % 2:
        a = np.pad(a, ((0, 0), (0, 1)))
        w = np.pad(w, ((0, 1), (0, 0)))
    products = a.astype(np.int32)[:, :, None] * w.astype(np.int32)[None]  # (M, K, N)
    pairs = products[:, 0::2] + products[:, 1::2]  # (M, K/2, N): one VPMADDUBSW lane each
    return np.clip(pairs, INT16_MIN, INT16_MAX).sum(axis=1, dtype=np.int64)


def weights_fit_avx2(w: np.ndarray) -> bool:
    """True when no pair of products with these int8 weights can saturate (all within +-64)."""
    return bool(np.abs(np.asarray(w, np.int32)).max(initial=0) <= AVX2_SAFE_WEIGHT)


def dot_as_onnxruntime_runs_it(a: np.ndarray, w: np.ndarray, kernel: str, precision_mode: bool) -> np.ndarray:
    """The int32 accumulators of onnxruntime's U8S8 convolution on a CPU whose INT8 kernel is ``kernel``
    (:func:`geonet_infer.engines.cpu.int8_kernel`: "amx_int8", "vnni", "avx2", ...), with or without
    ``session.x64quantprecision`` (``precision_mode``)."""
    if kernel != "avx2" or (precision_mode and not weights_fit_avx2(w)):
        return dot_exact(a, w)  # VNNI/AMX, or the remedy's U8U8 kernels
    return dot_avx2_u8s8(a, w)


def conv_weights(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    """The int8 weight tensor of every quantised Conv of a QDQ graph, by Conv node name."""
    inits = {i.name: i for i in model.graph.initializer}
    dq = {n.output[0]: n for n in model.graph.node if n.op_type == "DequantizeLinear"}
    out = {}
    for node in model.graph.node:
        source = dq.get(node.input[1]) if node.op_type == "Conv" and len(node.input) > 1 else None
        if source is not None and source.input[0] in inits:
            w = numpy_helper.to_array(inits[source.input[0]])
            if w.dtype == np.int8:
                out[node.name] = w
    return out


def int8_kernels(model: onnx.ModelProto) -> dict:
    """Which x86 INT8 kernels compute this QDQ graph's convolutions exactly (for the manifest).

    ``vnni`` and ``amx`` always; ``avx2_u8s8`` (plain AVX2 kernels, e.g. another program's
    onnxruntime session or OpenVINO on an AVX2-only CPU) only if every int8 weight fits +-64;
    ``avx2_onnxruntime_precision_mode`` always (onnxruntime then runs the overflowing convs
    exactly, :func:`dot_as_onnxruntime_runs_it`). ``convs_over_avx2_bound`` counts the convs
    whose weights exceed +-64.
    """
    over = [name for name, w in conv_weights(model).items() if not weights_fit_avx2(w)]
    return {
        "vnni": True,
        "amx": True,
        "avx2_u8s8": not over,
        "avx2_onnxruntime_precision_mode": True,
        "convs_over_avx2_bound": len(over),
    }
