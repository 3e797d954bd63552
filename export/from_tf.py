"""The released GeoNet TensorFlow checkpoints and our PyTorch nets: the layer mapping, and
``python -m export --from-tf`` (docs/official_models.md).

The conversion itself is the runtime's (:mod:`geonet_infer.convert`: numpy, no torch): it fills
architecture templates with the checkpoint's tensors. This module holds what needs torch:

- :func:`expected_variables`: the variables our layers (``export.templates.torch_layers``, in the
  official creation order) take, checked against the official list by the tests;
- :func:`convert_network`: a PyTorch net holding a checkpoint's tensors (the tests' reference: the
  torch exporter's graph of the same checkpoint);
- :func:`tf_export`: ``--from-tf`` at any size (templates made for it here) and ``--verify``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from export.templates import torch_layers
from geonet_infer import conventions
from geonet_infer.convert.official import (
    BN_VARIABLES,
    SCOPES,
    NetSpec,
    TFCheckpoint,
    check_variables,
    layer_name,
)
from geonet_infer.errors import InputError


# ------------------------------------------------------------------------------ our layers
def expected_variables(kind: str, net: nn.Module) -> list[tuple[str, list[int], str]]:
    """(name, TF shape, dtype) of every checkpoint variable ``net`` needs, in creation order."""
    scope = SCOPES[kind]
    out = []
    for i, (conv, bn) in enumerate(torch_layers(net)):
        o, c, kh, kw = conv.weight.shape
        prefix = f"{scope}/{layer_name(i)}"
        out.append((f"{prefix}/weights", [kh, kw, c, o], "float32"))
        tails = BN_VARIABLES if bn is not None else ("biases",)
        out += [(f"{prefix}/{tail}", [o], "float32") for tail in tails]
    return out


def build_network(kind: str, arch: str | None = None, num_source: int | None = None) -> nn.Module:
    """Our (eval-mode) network for an official one: DepthNet resnet50/vgg, PoseNet, ResFlowNet."""
    from training.networks import DepthNet, PoseNet, ResFlowNet

    if kind == "depth":
        return DepthNet(arch).eval()
    if kind == "pose":
        return PoseNet(num_source, arch="standard").eval()
    return ResFlowNet("resnet50").eval()


def convert_network(ckpt: TFCheckpoint, spec: NetSpec, net: nn.Module | None = None) -> nn.Module:
    """Our network (``net``, or a new one for ``spec``) with every parameter and BN statistic set from ``ckpt``.

    Every ``<scope>/`` variable is consumed exactly once; a missing, left-over or misshapen
    variable is a GeoNetError naming it. HWIO weights become OIHW. (``num_batches_tracked``,
    a PyTorch training counter unused in eval mode, stays 0.)
    """
    net = net.eval() if net is not None else build_network(spec.kind, spec.arch, spec.num_source)
    check_variables(ckpt, spec)
    assigned = set()
    with torch.no_grad():
        for i, (conv, bn) in enumerate(torch_layers(net)):
            prefix = f"{SCOPES[spec.kind]}/{layer_name(i)}"
            conv.weight.copy_(torch.from_numpy(ckpt.tensor(f"{prefix}/weights").transpose(3, 2, 0, 1).copy()))
            assigned.add(id(conv.weight))
            if bn is None:
                targets = {"biases": conv.bias}
            else:
                targets = dict(zip(BN_VARIABLES, (bn.bias, bn.running_mean, bn.running_var)))
            for tail, target in targets.items():
                target.copy_(torch.from_numpy(ckpt.tensor(f"{prefix}/{tail}")))
                assigned.add(id(target))
    unset = [n for n, t in (*net.named_parameters(), *net.named_buffers()) if id(t) not in assigned]
    unset = [n for n in unset if not n.endswith("num_batches_tracked")]
    if unset:  # a mapping bug, not a user error: torch_layers missed a layer
        raise AssertionError(f"parameters not set by the checkpoint: {unset[:5]}")
    return net


# ------------------------------------------------------------------------------ --from-tf
def torch_reference(sel, scale_normalize: bool):
    """``--verify``'s fallback without TensorFlow: our PyTorch nets holding the checkpoint's tensors
    (checks the ONNX export, not the mapping; the mapping is checked by the tests against TensorFlow)."""
    from export.verify import torch_outputs
    from export.wrappers import build_wrapper
    from geonet_infer.convert.verify import OUTPUTS
    from training.model import GeoNet

    built: dict = {}

    def reference(graph: str, feed: np.ndarray):
        if "model" not in built:
            model = GeoNet(
                sel.arch, sel.seq_length() - 1, with_flow="flow" in sel.specs, scale_normalize=scale_normalize
            ).eval()
            nets = {"depth": model.depth_net, "pose": model.pose_net, "flow": model.flow_net}
            for kind, spec in sel.specs.items():
                convert_network(sel.checkpoints[kind], spec, nets[kind])
            built["model"] = model
        wrapper = build_wrapper(graph, built["model"])
        names = [n for n, _ in _io_outputs(graph, feed)]
        out = dict(zip(names, torch_outputs(wrapper, [feed])))[OUTPUTS[graph][1]]
        return out, "our PyTorch nets with the checkpoint's tensors (checks the export, not the mapping)"

    return reference


def _io_outputs(graph: str, feed: np.ndarray):
    from export.wrappers import io_spec

    return io_spec(graph, feed.shape[2], feed.shape[3], 3).outputs


def needed_templates(sel, scale_normalize: bool) -> list[tuple[str, str, int, bool]]:
    """(graph, arch, seq_length, scale_normalize) of every template the selected networks need."""
    arch, seq_length = sel.arch, sel.seq_length()
    wanted = [("rigidflow", "resnet50", 3, False)]
    if "depth" in sel.specs:
        wanted.append(("depthnet", arch, 3, scale_normalize))
    if "pose" in sel.specs:
        wanted.append(("posenet", "resnet50", seq_length, False))
    if "flow" in sel.specs:
        wanted.append(("resflownet", "resnet50", 3, False))
    return wanted


def tf_export(cfg, log=print) -> Path:
    """``python -m export --from-tf``: the runtime's conversion (:func:`geonet_infer.convert.build.convert`)
    with templates made here by the torch exporter for the asked size (the shipped ones at 128x416),
    and ``--verify`` before the directory is published."""
    from export.source import check_graph_size
    from export.templates import make_templates
    from geonet_infer.convert.build import ConvertConfig, convert
    from geonet_infer.convert.official import select_networks
    from geonet_infer.convert.templates import TEMPLATES_DIR
    from geonet_infer.convert.verify import verify

    height = cfg.height or conventions.REFERENCE_HEIGHT
    width = cfg.width or conventions.REFERENCE_WIDTH
    check_graph_size(height, width)  # before minutes of reading checkpoints
    if cfg.eval_synth_dir:
        raise InputError(None, "--eval-synth-dir applies to our own checkpoints", "score converted models with eval")
    sel = select_networks(cfg.from_tf, log=lambda _: None)
    arch = sel.arch
    if cfg.arch and cfg.arch != arch:
        raise InputError(None, f"the checkpoint's depth_net is {arch}, --arch says {cfg.arch}", "drop --arch")
    seq_length = sel.seq_length(default=cfg.seq_length or 3)
    if cfg.seq_length and cfg.seq_length != seq_length:
        raise InputError(
            None, f"the checkpoint's pose_net takes {seq_length}-frame snippets, --seq-length says {cfg.seq_length}"
        )

    def check(model_dir: Path) -> None:
        from export.to_onnx import ExportCheckError
        from geonet_infer.convert.verify import VerifyError

        reference = torch_reference(sel, cfg.scale_normalize)
        try:
            line = verify(
                model_dir,
                sel,
                cfg.verify,
                height=height,
                width=width,
                seq_length=seq_length,
                scale_normalize=cfg.scale_normalize,
                reference=reference,
            )
        except VerifyError as err:  # exit code 1 (a conversion that is wrong), not 2 (bad input)
            raise ExportCheckError(err.problem) from None
        print(line, flush=True)  # asked for: printed even with --quiet

    with tempfile.TemporaryDirectory() as tmp:
        templates = TEMPLATES_DIR
        if (height, width) != (conventions.REFERENCE_HEIGHT, conventions.REFERENCE_WIDTH):
            templates = Path(tmp)
            make_templates(templates, height, width, needed_templates(sel, cfg.scale_normalize), log=lambda _: None)
        return convert(
            ConvertConfig(
                checkpoints=tuple(cfg.from_tf),
                out=Path(cfg.out),
                precisions=tuple(cfg.precisions),
                calib_data=cfg.calib_data,
                quant=cfg.quant_settings(),
                scale_normalize=cfg.scale_normalize,
                graphs=tuple(cfg.graphs),
                templates=templates,
                force=cfg.force,
                log=log,
                before_publish=check if cfg.verify else None,
            )
        )
