"""The runtime's conversion against the torch exporter (issue 52), where torch is installed.

``tests/runtime/convert/test_convert.py`` checks ``geonet-infer convert`` (torch blocked) against stored
reference outputs; here those are re-made from live torch exports, and the shipped templates are
re-made from the current networks, so neither can go stale.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from export.templates import SHIPPED, make_template
from geonet_infer.convert.templates import TEMPLATES_DIR, template_name
from tests.conftest import require_realdata


@pytest.mark.slow
def test_stored_reference_outputs_are_the_torch_exporters(tmp_path):
    from tests.runtime.convert.fixtures.write_reference import reference_outputs
    from tests.runtime.convert.test_convert import FRAMES, REFERENCE

    live = reference_outputs(tmp_path, require_realdata(FRAMES))
    stored = np.load(REFERENCE)
    assert sorted(live) == sorted(stored.files)
    for key, value in live.items():
        assert float(np.abs(value - stored[key]).max()) <= 1e-6, key


@pytest.mark.slow
@pytest.mark.parametrize("graph, arch, seq_length, sn", SHIPPED, ids=lambda v: str(v))
def test_shipped_templates_are_what_the_exporter_makes_now(tmp_path, graph, arch, seq_length, sn):
    """Same weights in the same order with the same rules, and the same nodes: a network changed in
    training/ without `python -m export.templates` fails here. Made at 64x224 (twice as fast): the
    weights and the nodes do not depend on the image size, only the I/O shapes do."""
    name = template_name(graph, arch=arch, seq_length=seq_length, sn=sn)
    fresh = json.loads(make_template(graph, arch, seq_length, sn, 64, 224, tmp_path).read_text())
    shipped = json.loads((TEMPLATES_DIR / f"{name}.json").read_text())
    for recipe in (fresh, shipped):
        for key in ("made_with", "height", "width", "io"):
            recipe.pop(key)
    assert fresh == shipped
    ops = [[n.op_type for n in onnx.load(str(d / f"{name}.onnx")).graph.node] for d in (tmp_path, TEMPLATES_DIR)]
    assert ops[0] == ops[1]


def test_the_bn_fold_rule_is_the_exporters():
    """A conv + BatchNorm layer exported by torch (its fold by onnxscript) against the recipe's numpy
    rule on the same values: bit for bit."""
    import torch

    from export.to_onnx import export_graph
    from export.wrappers import IOSpec
    from geonet_infer.convert.templates import compute
    from training.networks.blocks import BatchNormNoScale

    class Layer(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv2d(3, 5, 3, bias=False)
            self.bn = BatchNormNoScale(5)

        def forward(self, x):
            return self.bn(self.conv(x))

    g = torch.Generator().manual_seed(0)
    layer = Layer().eval()
    with torch.no_grad():
        layer.conv.weight.copy_(torch.randn(5, 3, 3, 3, generator=g))
        layer.bn.running_mean.copy_(torch.randn(5, generator=g))
        layer.bn.running_var.copy_(torch.rand(5, generator=g) + 0.5)
        layer.bn.bias.copy_(torch.randn(5, generator=g))
    values = {
        "L/weights": layer.conv.weight.detach().numpy().transpose(2, 3, 1, 0),
        "L/BatchNorm/moving_mean": layer.bn.running_mean.numpy(),
        "L/BatchNorm/moving_variance": layer.bn.running_var.numpy(),
        "L/BatchNorm/beta": layer.bn.bias.detach().numpy(),
    }

    class Checkpoint:  # the one method compute() reads
        def tensor(self, name):
            return values[name]

    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        spec = IOSpec(inputs=(("x", ("B", 3, 8, 8)),), outputs=(("y", ("B", 5, 6, 6)),))
        export_graph(layer, (torch.randn(1, 3, 8, 8),), spec, Path(tmp) / "l.onnx")
        inits = {i.name: onnx.numpy_helper.to_array(i) for i in onnx.load(str(Path(tmp) / "l.onnx")).graph.initializer}
    rules = {name: {**rule, "layer": "L"} for name, rule in recipe_rules_for(layer).items()}
    assert set(rules) == set(inits)
    for name, rule in rules.items():
        ours = compute(Checkpoint(), {"name": name, "dims": list(inits[name].shape), **rule})
        assert ours.tobytes() == inits[name].tobytes(), name


def recipe_rules_for(layer):
    """The rules for the one layer of the test above (``recipe_rules`` walks whole GeoNet networks)."""
    return {
        "conv.weight": {"rule": "conv_bn", "eps": layer.bn.eps},
        "conv.weight_bias": {"rule": "conv_bn_bias", "eps": layer.bn.eps},
    }
