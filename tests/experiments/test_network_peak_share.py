"""experiments/network_peak_share.py's arithmetic on hand-made timings: GOP/s = 2 MACs / time, the share of
the measured int8 peak, and a frame's networks on each graph's fastest engine and precision."""

from __future__ import annotations

import pytest

from experiments import network_peak_share as nps

MACS = {"depthnet": 4e8, "posenet": 1e8, "resflownet": 5e8}


def bench_result(*_args) -> dict:
    rows = [
        ("depth", "onnxruntime", "int8", 8.0),
        ("depth", "openvino", "int8", 4.0),
        ("pose", "onnxruntime", "fp32", 2.0),
        ("resflow", "openvino", "int8", 10.0),
        ("resflow", "onnxruntime", "fp32", 12.5),
    ]
    results = [{"task": t, "backend": b, "precision": p, "p50_ms": ms} for t, b, p, ms in rows]
    return {"results": results, "environment": {"cpu": "test CPU", "cpu_flags": ["avx2"]}}


def test_shares_and_the_frame_on_the_fastest_of_each(monkeypatch):
    monkeypatch.setattr(nps, "bench_graphs", bench_result)
    monkeypatch.setattr(nps.target_limits, "gemm_peaks", lambda threads: {"int8_gops": 500.0, "fp32_gflops": 100.0})
    monkeypatch.setattr(nps.target_limits, "graph_macs", lambda path, skip_zero_taps: MACS[path.stem])
    result = nps.shares("small_synth", 2, "onnxruntime,openvino", 5)
    depth_ov = next(r for r in result["rows"] if r["graph"] == "depthnet" and r["engine"] == "openvino")
    assert depth_ov["gops"] == pytest.approx(2 * 4e8 / 4e-3 / 1e9)  # 200 GOP/s
    assert depth_ov["share_of_int8_peak"] == pytest.approx(0.4)
    frame = result["per_frame"]
    assert frame["best"] == {"depthnet": "openvino int8", "posenet": "onnxruntime fp32", "resflownet": "openvino int8"}
    assert frame["ms"] == pytest.approx(4.0 + 2.0 + 10.0)
    assert frame["share_of_int8_peak"] == pytest.approx(2 * 10e8 / 16e-3 / 1e9 / 500.0)  # 125 of 500 GOP/s
    assert frame["ms_at_int8_peak"] == pytest.approx(2 * 10e8 / 500e9 * 1e3)
    assert "**25%**" in nps.markdown(result)
