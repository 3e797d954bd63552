"""The peer depth networks of ``experiments/peer_models.py`` (issue 44): sizes, exports, counters.

Golden values are the authors' own figures, typed here from their papers / repositories (not read
from the module under test), and hand-computed MACs of a two-layer graph.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from experiments import peer_nets  # noqa: E402
from experiments.peer_models import (  # noqa: E402
    PEERS,
    build_module,
    contradictions,
    export_peer,
    graph_macs_all,
    main,
    prepare,
    rankings,
    replace_section,
    tied_rankings,
)
from geonet_infer.engines import make_engine  # noqa: E402

# Parameters the authors state, and where: the rebuild must be within 2 %.
PAPER_PARAMS = {
    "Monodepth2": 14.3e6,  # Lite-Mono paper (CVPR 2023) Table 1, Monodepth2 R18
    "LiteMono": 3.1e6,  # github.com/noahzn/Lite-Mono README, lite-mono
    "MidasSmall": 21e6,  # github.com/isl-org/MiDaS README, v2.1 Small 256, "Par. M"
    "DepthAnythingV2Small": 24.8e6,  # github.com/DepthAnything/Depth-Anything-V2 README, Small
}


@pytest.mark.parametrize("builder", sorted(PAPER_PARAMS))
def test_parameter_count_within_2_percent_of_the_paper(builder):
    n = sum(p.numel() for p in getattr(peer_nets, builder)().parameters())
    assert abs(n / PAPER_PARAMS[builder] - 1) <= 0.02, (builder, n)


def test_the_page_quotes_the_same_paper_figures():
    assert {p.builder: p.params_ref for p in PEERS.values()} == PAPER_PARAMS


def test_efficientnet_lite3_features_have_the_widths_midas_reads():
    # MiDaS blocks.py: _make_scratch([32, 48, 136, 384], ...) for efficientnet_lite3, at 1/4 .. 1/32
    feats = peer_nets.EfficientNetLite3().eval()(torch.zeros(1, 3, 64, 96))
    assert [tuple(f.shape[1:]) for f in feats] == [(32, 16, 24), (48, 8, 12), (136, 4, 6), (384, 2, 3)]


# Output per each model's code: monodepth2 / Lite-Mono a sigmoid disparity (B, 1, H, W) at the input
# size (scale 0); MiDaS and Depth-Anything-V2 squeeze the channel: (B, H, W). Small inputs keep it fast
# (each side divisible by 32 for the ConvNets, by 14 for the ViT).
SHAPES = {
    "monodepth2": ((64, 96), (1, 1, 64, 96)),
    "litemono": ((64, 96), (1, 1, 64, 96)),
    "midas_small": ((64, 96), (1, 64, 96)),
    "dav2_small": ((42, 56), (1, 42, 56)),
}


@pytest.mark.parametrize("key", sorted(SHAPES))  # 2-10 s each (export + INT8) on 2 cores
def test_onnx_export_runs_on_onnxruntime_with_the_stated_output_shape(key, tmp_path):
    size, shape = SHAPES[key]
    peer = PEERS[key]
    rng = np.random.default_rng(0)
    calib = [rng.integers(0, 256, (100, 150, 3), dtype=np.uint8) for _ in range(2)]
    export_peer(peer, size, tmp_path, calib, seed=3)
    x = prepare(calib[0], size, *peer.norm)
    with torch.no_grad():
        ref = build_module(peer, seed=3)(torch.from_numpy(x)).numpy()
    assert ref.shape == shape == peer.out_shape(*size)
    for precision in ("fp32", "int8"):
        engine = make_engine(tmp_path / f"{precision}.onnx", "onnxruntime", 1)  # the runtime's own sessions
        out = engine.run({"image": x})["depth"]
        assert out.shape == shape, precision
        assert np.isfinite(out).all()
        if precision == "fp32":  # the graph computes what the module computes
            np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-4 * float(np.abs(ref).max()))


def test_graph_macs_counts_convolutions_and_matrix_products(tmp_path):
    class Tiny(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv2d(3, 8, 3, padding=1)
            self.fc = torch.nn.Linear(10, 5)

        def forward(self, x):
            return self.conv(x), self.fc(x[:, 0, :4, :])

    path = tmp_path / "tiny.onnx"
    torch.onnx.export(Tiny(), (torch.zeros(1, 3, 10, 10),), str(path), dynamo=False, opset_version=18)
    conv = 8 * 10 * 10 * (3 * 3 * 3)  # every output element: 3 input channels x 3 x 3
    linear = 4 * 5 * 10  # 4 rows x 5 outputs x 10 inputs
    assert graph_macs_all(path) == conv + linear


@pytest.mark.parametrize("key", ["monodepth2", "midas_small"])
def test_graph_macs_of_a_convnet_equal_the_forward_hook_count(key, tmp_path):
    # Both are Conv2d-only networks: training.summary's hook counter (out elements x in/groups x kh x kw,
    # counted in PyTorch) is an independent count; the ONNX one must follow every TF-"same" pad too.
    from training.summary import count_params_and_macs

    module = build_module(PEERS[key])
    path = tmp_path / "g.onnx"
    torch.onnx.export(module, (torch.zeros(1, 3, 64, 96),), str(path), dynamo=False, opset_version=18)
    assert graph_macs_all(path) == count_params_and_macs(module, (1, 3, 64, 96))[1]


def test_prepare_resizes_and_normalises_per_channel():
    rgb = np.zeros((20, 40, 3), np.uint8)
    rgb[..., 0] = 255
    mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    x = prepare(rgb, (10, 20), mean, std)
    assert x.shape == (1, 3, 10, 20) and x.dtype == np.float32
    np.testing.assert_allclose(x[0, :, 0, 0], [(1 - 0.485) / 0.229, -0.456 / 0.224, -0.406 / 0.225], rtol=1e-6)


def test_replace_section_rewrites_only_its_own_section(tmp_path):
    page = tmp_path / "performance.md"
    page.write_text("# P\n\n## A\n\na\n\n## Versus the models users pick instead\n\nold\n\n## B\n\nb\n")
    replace_section(page, "## Versus the models users pick instead\n\nnew\n\n")
    assert page.read_text() == "# P\n\n## A\n\na\n\n## Versus the models users pick instead\n\nnew\n\n## B\n\nb\n"
    other = tmp_path / "other.md"
    other.write_text("# Q\n")
    replace_section(other, "## Versus the models users pick instead\n\nx\n")
    assert other.read_text() == "# Q\n\n## Versus the models users pick instead\n\nx\n"


def test_rankings_per_configuration_and_at_each_models_best():
    def row(model, which, precision, backend, ms):
        return {"model": model, "which": which, "precision": precision, "backend": backend, "mode": "e2e", "p50_ms": ms}

    results = [
        row("geonet", "ours", "fp32", "onnxruntime", 30.0),
        row("geonet", "ours", "int8", "onnxruntime", 50.0),
        row("a", "ours", "fp32", "onnxruntime", 20.0),
        row("a", "ours", "int8", "onnxruntime", 60.0),
        row("b", "ours", "fp32", "onnxruntime", 40.0),
        row("b", "ours", "int8", "onnxruntime", 10.0),
        row("a", "native", "fp32", "onnxruntime", 90.0),
    ]
    r = rankings(results)
    assert r["ours/fp32/onnxruntime/e2e"] == ["a", "geonet", "b"]
    assert r["ours/int8/onnxruntime/e2e"] == ["b", "geonet", "a"]
    assert r["ours/best/e2e"] == ["b", "a", "geonet"]  # b 10, a 20, geonet 30
    assert r["native/best/e2e"] == ["geonet", "a"]  # GeoNet's 128x416 is its native size too


def test_models_whose_quartiles_overlap_are_tied_and_only_opposite_strict_orders_contradict():
    def row(model, q1, p50, q3):
        return {
            "model": model,
            "which": "ours",
            "precision": "fp32",
            "backend": "onnxruntime",
            "mode": "e2e",
            "p50_ms": p50,
            "q1_ms": q1,
            "q3_ms": q3,
        }

    # a [9, 11] and b [10.5, 12] overlap; c [20, 22] is apart; d [21.5, 23] overlaps c: two ties, one order.
    results = [row("c", 20, 21, 22), row("a", 9, 10, 11), row("d", 21.5, 22, 23), row("b", 10.5, 11, 12)]
    tied = tied_rankings(results)["ours/fp32/onnxruntime/e2e"]
    assert tied == [["a", "b"], ["c", "d"]]
    assert contradictions(tied, [["b"], ["a"], ["d", "c"]]) == []  # a/b ordered in one run, tied in the other
    assert contradictions(tied, [["c"], ["a", "b", "d"]]) == [("a", "c"), ("b", "c")]
    assert contradictions([["a"], ["b"]], [["b"], ["a"]]) == [("a", "b")]


DOCS = Path(__file__).resolve().parents[2] / "docs"


def test_the_page_section_is_what_render_makes_of_the_two_committed_runs(tmp_path):
    """docs/performance.md's peer section is exactly what the command named there renders from the
    committed JSONs (no hand edits, no drift), and a missing --render file is a one-line error."""
    page = tmp_path / "performance.md"
    page.write_text((DOCS / "performance.md").read_text())
    argv = ["--render", str(DOCS / "peer_models_run2.json"), "--compare", str(DOCS / "peer_models_run1.json")]
    assert main([*argv, "--page", str(page)]) == 0
    assert page.read_text() == (DOCS / "performance.md").read_text()
    assert main(["--render", str(tmp_path / "missing.json")]) == 2
