"""Write a TensorFlow checkpoint in the layout of a released GeoNet checkpoint, with random values.

The released files cannot be downloaded on this project's machines; this stands in for them so that
every command of docs/official_models.md can be run as written (the values are random: the depth,
poses and flow it gives mean nothing). Names, shapes and dtypes come from
geonet_infer/convert/official_variables.json (derived from the official code); the files are written by
geonet_infer/convert/tf_checkpoint.py (no TensorFlow needed; TensorFlow reads them,
tests/export/test_tf_checkpoint.py)::

    python -m geonet_infer.convert.random_checkpoint /tmp/geonet_depthnet/model-250000 depth_resnet50 pose_seq3
    python -m geonet_infer.convert.random_checkpoint /tmp/geonet_posenet/model-206000 depth_resnet50 pose_seq5
    python -m geonet_infer.convert.random_checkpoint /tmp/geonet_resflownet/model-400000 \\
        depth_resnet50 pose_seq3 flow_resnet50

A ``train_rigid`` release holds depth_net and pose_net, a ``train_flow`` release flow_net as well
(../shared/reference/official_checkpoints.md), plus ``global_step``.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

from geonet_infer.convert.official import official_variables
from geonet_infer.convert.tf_checkpoint import write_checkpoint


def random_values(variables: list, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """He-scaled weights, BatchNorm at its initial statistics, small betas and biases.

    The last 1x1 conv of each bottleneck (``Conv_N`` whose output width is 4x its input, and the
    shortcut) is scaled down so 16 random residual blocks do not grow activations without bound."""
    values = {}
    for name, shape, dtype in variables:
        if name.endswith("/weights"):
            fan_in = int(np.prod(shape[:-1]))
            std = np.sqrt(2.0 / fan_in) * (0.25 if len(shape) == 4 and shape[-1] >= 4 * shape[-2] else 1.0)
            value = rng.normal(0.0, std, shape)
        elif name.endswith("moving_variance"):
            value = np.ones(shape)
        elif name.endswith("moving_mean"):
            value = np.zeros(shape)
        else:  # BatchNorm/beta, biases
            value = rng.normal(0.0, 0.01, shape)
        values[name] = value.astype(dtype)
    return values


def main(argv: list[str] | None = None) -> int:
    networks = official_variables()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("prefix", type=Path, help="checkpoint prefix to write: PREFIX.index + PREFIX.data-*")
    parser.add_argument("networks", nargs="+", choices=list(networks), help="networks the checkpoint holds")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    values = {}
    for key in args.networks:
        values.update(random_values(networks[key], rng))
    step = int(m.group(1)) if (m := re.search(r"model-(\d+)$", args.prefix.name)) else 0
    write_checkpoint(args.prefix, {**values, "global_step": np.int64(step)})
    print(f"{args.prefix}: {len(values)} variables of {', '.join(args.networks)} (random values), global_step {step}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
