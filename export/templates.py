"""Make the conversion templates of ``geonet_infer/convert/templates/`` with the torch exporter.

    python -m export.templates                   # the shipped set, 128x416 (a few minutes)
    python -m export.templates --out DIR --height 64 --width 224

Each template is the graph ``export.to_onnx.export_graph`` makes of our network (random weights),
with every initializer that holds a checkpoint variable removed and named in the recipe instead
(:mod:`geonet_infer.convert.templates` says the format). Which initializer is which comes from
:func:`torch_layers` (our layers in the official creation order: layer i is slim's ``Conv_i``) and the parameter
names the exporter keeps; an initializer it cannot place fails the build, so a changed exporter
cannot ship a template that silently keeps random weights.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import onnx
import torch.nn as nn

from export.to_onnx import OPSET, ExportCheckError, export_graph
from export.wrappers import build_wrapper, example_inputs, io_spec, photometric_alpha
from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH
from geonet_infer.convert.official import layer_name
from geonet_infer.convert.templates import RECIPE_FORMAT, TEMPLATES_DIR, template_name

# (graph, arch, seq_length, scale_normalize) of every released network, and the weightless rigid op.
SHIPPED = (
    ("depthnet", "resnet50", 3, False),
    ("depthnet", "resnet50", 3, True),  # the model_sn release
    ("depthnet", "vgg", 3, False),
    ("posenet", "resnet50", 3, False),
    ("posenet", "resnet50", 5, False),
    ("resflownet", "resnet50", 3, False),
    ("rigidflow", "resnet50", 3, False),
)
NET_OF_GRAPH = {"depthnet": "depth_net", "posenet": "pose_net", "resflownet": "flow_net"}


def torch_layers(net: nn.Module) -> list[tuple[nn.Conv2d, nn.Module | None]]:
    """(conv, batch norm or None) of ``net`` in the official code's creation order (``Conv_i`` = item i).

    DepthNet/ResFlowNet resnet50: conv1, per bottleneck conv1, conv2, conv3, shortcut (``resconv``),
    then per decoder level upconv, iconv and (the last four levels) the prediction head. VGG: the
    7 encoder pairs, then the same decoder. PoseNet: 7 convs, then the 1x1 pose conv.
    """
    from training.networks import DepthNet, PoseNet, ResFlowNet
    from training.networks.depthnet import VGGEncoder

    def block(b) -> tuple[nn.Conv2d, nn.Module]:
        return b.conv, b.bn

    layers = []
    if isinstance(net, PoseNet):
        layers += [block(b) for b in net.convs]
        return layers + [(net.pose_pred, None)]
    if not isinstance(net, (DepthNet, ResFlowNet)):
        raise TypeError(f"not a GeoNet network: {type(net).__name__}")
    enc, dec = net.encoder, net.decoder
    if isinstance(enc, VGGEncoder):
        layers += [block(b) for pair in enc.pairs for b in pair]
    else:
        layers.append(block(enc.conv1))
        for stage in enc.stages:
            for bottleneck in stage:
                layers += [block(getattr(bottleneck, n)) for n in ("conv1", "conv2", "conv3", "shortcut")]
    first_pred_level = dec.num_levels - dec.num_preds
    for level in range(dec.num_levels):
        layers += [block(dec.upconvs[level].conv), block(dec.iconvs[level])]
        if level >= first_pred_level:
            layers.append((dec.heads[dec.num_levels - 1 - level].conv, None))
    return layers


def recipe_rules(wrapper, net) -> dict[str, dict]:
    """Exported initializer name -> rule, for every weight of ``net`` inside ``wrapper``."""
    names = {id(p): n for n, p in wrapper.named_parameters()}
    rules = {}
    for i, (conv, bn) in enumerate(torch_layers(net)):
        weight, layer = names[id(conv.weight)], layer_name(i)
        if bn is None:
            rules[weight] = {"rule": "conv", "layer": layer}
            rules[names[id(conv.bias)]] = {"rule": "bias", "layer": layer}
        else:  # the exporter folds the BatchNorm into the conv: weight and a new "<weight>_bias"
            rules[weight] = {"rule": "conv_bn", "layer": layer, "eps": bn.eps}
            rules[f"{weight}_bias"] = {"rule": "conv_bn_bias", "layer": layer, "eps": bn.eps}
    return rules


def _distinct_values(model) -> None:
    """Random BatchNorm statistics and biases: at their initial values (zeros) several folded biases
    would hold the same bytes, and the exporter would merge them into one initializer."""
    import torch

    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, tensor in (*model.named_parameters(), *model.named_buffers()):
            if name.endswith(("running_mean", "bias")):
                tensor.copy_(torch.randn(tensor.shape, generator=generator) * 0.1)
            elif name.endswith("running_var"):
                tensor.copy_(torch.rand(tensor.shape, generator=generator) + 0.5)


def make_template(
    graph: str, arch: str, seq_length: int, scale_normalize: bool, height: int, width: int, out: Path
) -> Path:
    """Write ``out/<name>.onnx`` and ``out/<name>.json``; returns the .json path."""
    from export.manifest import versions
    from training.model import GeoNet

    model = GeoNet(arch, seq_length - 1, with_flow=graph == "resflownet", scale_normalize=scale_normalize).eval()
    _distinct_values(model)
    wrapper = build_wrapper(graph, model)
    spec = io_spec(graph, height, width, seq_length)
    with tempfile.TemporaryDirectory() as tmp:
        result = export_graph(wrapper, example_inputs(graph, height, width, seq_length), spec, Path(tmp) / "g.onnx")
        proto = onnx.load(str(result.path))
    rules = recipe_rules(wrapper, getattr(model, NET_OF_GRAPH[graph])) if graph in NET_OF_GRAPH else {}
    recipe, keep = [], []
    for init in proto.graph.initializer:
        if init.name in rules:
            if init.data_type != onnx.TensorProto.FLOAT:
                raise ExportCheckError(f"{init.name}: a weight of type {init.data_type}, expected float32")
            recipe.append({"name": init.name, "dims": list(init.dims), **rules[init.name]})
        else:
            keep.append(init)
    missing = sorted(set(rules) - {r["name"] for r in recipe})
    if missing:
        raise ExportCheckError(f"{graph}: the exporter no longer names these weights as expected: {missing[:3]}")
    del proto.graph.initializer[:]
    proto.graph.initializer.extend(keep)
    del proto.metadata_props[:]  # written per model by the converter
    name = template_name(graph, arch=arch, seq_length=seq_length, sn=scale_normalize)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.onnx").write_bytes(proto.SerializeToString())
    meta = {
        "format": RECIPE_FORMAT,
        "graph": graph,
        "arch": arch if graph in ("depthnet", "resflownet") else None,
        "seq_length": seq_length if graph == "posenet" else None,
        "scale_normalize": scale_normalize if graph == "depthnet" else None,
        "height": height,
        "width": width,
        "opset": OPSET,
        "exporter": result.exporter,
        "made_with": versions(),
        "photometric_alpha": photometric_alpha(model),
        "io": {
            "inputs": [list(x) for x in spec.inputs],
            "outputs": [list(x) for x in spec.outputs],
            "dtype": spec.dtype,
        },
        "initializers": recipe,
    }
    path = out / f"{name}.json"
    path.write_text(json.dumps(meta, indent=1) + "\n")
    return path


def make_templates(out: Path, height: int, width: int, wanted=SHIPPED, log=print) -> list[Path]:
    made = []
    for graph, arch, seq_length, sn in wanted:
        made.append(make_template(graph, arch, seq_length, sn, height, width, out))
        log(f"  {made[-1].with_suffix('.onnx').name}  {made[-1].with_suffix('.onnx').stat().st_size / 1024:.0f} KiB")
    return made


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=TEMPLATES_DIR)
    parser.add_argument("--height", type=int, default=REFERENCE_HEIGHT)
    parser.add_argument("--width", type=int, default=REFERENCE_WIDTH)
    args = parser.parse_args(argv)
    make_templates(args.out, args.height, args.width)
    return 0


if __name__ == "__main__":
    sys.exit(main())
