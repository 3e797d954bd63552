"""Conversion as data: architecture-only ONNX graphs of the official networks plus a recipe per graph.

A template is two files in ``templates/`` beside this module, made once by the torch exporter
(``python -m export.templates``, repository only):

- ``NAME.onnx``: the exported graph with every weight-carrying initializer and the metadata removed
  (weight-independent constants stay);
- ``NAME.json``: the recipe: the graph's I/O, opset and exporter, and per removed initializer, in the
  exported order, its name, dims and how it is computed from the checkpoint's variables:

  =================  ==============================================================================
  ``conv``           ``<layer>/weights`` HWIO -> OIHW
  ``bias``           ``<layer>/biases``
  ``conv_bn``        ``<layer>/weights`` OIHW times ``1/sqrt(moving_variance + eps)`` per output channel
  ``conv_bn_bias``   ``(0 - moving_mean) / sqrt(moving_variance + eps) + beta``
  =================  ==============================================================================

  The two ``_bn`` rules are the exporter's own BatchNormalization fold (onnxscript's
  ``FuseBatchNormIntoConv``: ``W * gamma/std``, ``(b - mean) * gamma/std + beta``, slim's gamma = 1),
  in the same float32 order, so the converted graph holds the exporter's bytes.

Converting is reading the checkpoint and writing the graph (:mod:`.onnx_writer`): no torch, no onnx.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geonet_infer.convert.official import TFCheckpoint
from geonet_infer.errors import ModelError

TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"
RECIPE_FORMAT = "geonet-convert-recipe/1"
RULES = ("conv", "bias", "conv_bn", "conv_bn_bias")


@dataclass(frozen=True)
class Template:
    """One graph's template: ``head`` (its .onnx file) and ``recipe`` (its parsed .json)."""

    head: Path
    recipe: dict

    @property
    def graph(self) -> str:
        return self.recipe["graph"]

    @classmethod
    def load(cls, name: str, folder: Path = TEMPLATES_DIR) -> Template:
        head, recipe_path = folder / f"{name}.onnx", folder / f"{name}.json"
        try:
            recipe = json.loads(recipe_path.read_text())
        except (OSError, ValueError) as exc:
            raise ModelError(recipe_path, f"cannot read this conversion template ({exc})", REINSTALL) from None
        if recipe.get("format") != RECIPE_FORMAT or not head.is_file():
            raise ModelError(recipe_path, f"not a {RECIPE_FORMAT} template, or its .onnx is missing", REINSTALL)
        return cls(head, recipe)


REINSTALL = "the package's conversion templates are damaged: reinstall geonet-infer"


def template_name(graph: str, *, arch: str | None = None, seq_length: int | None = None, sn: bool = False) -> str:
    """The template file name of one graph (``depthnet_resnet50``, ``posenet_seq5``, ``rigidflow``...)."""
    if graph == "depthnet":
        return f"depthnet_{arch}" + ("_sn" if sn else "")
    if graph == "posenet":
        return f"posenet_seq{seq_length}"
    if graph == "resflownet":
        return "resflownet_resnet50"
    return "rigidflow"


def _bn_scale(ckpt: TFCheckpoint, layer: str, eps: float) -> np.ndarray:
    # float32 throughout, in onnxscript's order: gamma / sqrt(var + eps) with gamma = 1.
    var = ckpt.tensor(f"{layer}/BatchNorm/moving_variance")
    return np.float32(1.0) / np.sqrt(var + np.float32(eps))


def compute(ckpt: TFCheckpoint, entry: dict) -> np.ndarray:
    """One initializer of the recipe from the checkpoint's variables (float32, the recipe's dims)."""
    rule, layer = entry["rule"], entry["layer"]
    if rule in ("conv", "conv_bn"):
        value = np.ascontiguousarray(ckpt.tensor(f"{layer}/weights").transpose(3, 2, 0, 1))
        if rule == "conv_bn":
            value = value * _bn_scale(ckpt, layer, entry["eps"]).reshape(-1, 1, 1, 1)
    elif rule == "bias":
        value = ckpt.tensor(f"{layer}/biases")
    elif rule == "conv_bn_bias":
        mean = ckpt.tensor(f"{layer}/BatchNorm/moving_mean")
        beta = ckpt.tensor(f"{layer}/BatchNorm/beta")
        value = (np.zeros_like(mean) - mean) * _bn_scale(ckpt, layer, entry["eps"]) + beta
    else:
        raise ModelError(None, f"conversion rule {rule!r} unknown to this version", REINSTALL)
    value = np.ascontiguousarray(value, np.float32)
    if list(value.shape) != entry["dims"]:
        raise ModelError(
            None, f"{entry['name']}: the checkpoint gives {list(value.shape)}, the graph needs {entry['dims']}"
        )
    return value


def initializers(template: Template, ckpt: TFCheckpoint, scope: str) -> Iterator[tuple[str, np.ndarray]]:
    """(name, value) of every weight of ``template``'s graph, one at a time (the peak is one tensor)."""
    for entry in template.recipe["initializers"]:
        yield entry["name"], compute(ckpt, {**entry, "layer": f"{scope}/{entry['layer']}"})
