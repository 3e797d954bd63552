"""Derive geonet_infer/convert/official_variables.json from the official GeoNet code (not run by tests or CI).

Needs the official repository (https://github.com/yzcjtr/GeoNet, commit 5b17602) and, besides the
project's ``[tf]`` extra, ``tf-slim==1.1.0`` and ``tf-keras==2.21.0`` (not project dependencies)::

    pip install tensorflow-cpu==2.21.0 tf-slim==1.1.0 tf-keras==2.21.0
    git clone https://github.com/yzcjtr/GeoNet && git -C GeoNet checkout 5b17602
    python scripts/derive_official_variables.py GeoNet/geonet_nets.py 5b17602 \
        > geonet_infer/convert/official_variables.json

It builds each released network once at 128x416 with ``tensorflow.compat.v1`` and records every
model variable's name, shape and dtype in creation order (../shared/reference/official_checkpoints.md).
"""

from __future__ import annotations

import importlib
import json
import sys
import types
from pathlib import Path

HEIGHT, WIDTH = 128, 416
NETWORKS = {  # key -> (builder, kwargs, input channels)
    "depth_resnet50": ("disp_net", {"dispnet_encoder": "resnet50", "mode": "test_depth"}, 3),
    "depth_vgg": ("disp_net", {"dispnet_encoder": "vgg", "mode": "test_depth"}, 3),
    "pose_seq3": ("pose_net", {"num_source": 2, "mode": "test_pose"}, 9),
    "pose_seq5": ("pose_net", {"num_source": 4, "mode": "test_pose"}, 15),
    "flow_resnet50": ("flow_net", {"mode": "test_flow"}, 12),
}


def _load_official(nets_py: Path):
    """geonet_nets.py under TF 2 (see official_checkpoints.md): tf.compat.v1, tf_slim, int for np.int."""
    import tensorflow.compat.v1 as tf
    import tf_slim

    tf.disable_v2_behavior()
    # tf_slim's batch_norm reaches tf.compat.v1.layers, which TF 2.21 loads from tf_keras.legacy_tf_layers.
    for sub in ("", ".base", ".convolutional", ".core", ".normalization", ".pooling"):
        sys.modules[f"tf_keras.legacy_tf_layers{sub}"] = importlib.import_module(f"tf_keras.src.legacy_tf_layers{sub}")
    source = nets_py.read_text().replace("np.int(", "int(")
    source = source.replace("import tensorflow as tf", "import tensorflow.compat.v1 as tf")
    source = source.replace("import tensorflow.contrib.slim as slim", "import tf_slim as slim")
    module = types.ModuleType("geonet_nets")
    exec(compile(source, str(nets_py), "exec"), module.__dict__)
    return tf, tf_slim, module


def main(nets_py: str, commit: str) -> None:
    tf, tf_slim, nets = _load_official(Path(nets_py))
    out = {
        "about": (
            "Model variables (name, shape, dtype, creation order) of the official GeoNet networks, built once "
            f"at {HEIGHT}x{WIDTH} by scripts/derive_official_variables.py from yzcjtr/GeoNet geonet_nets.py"
        ),
        "official_code": f"https://github.com/yzcjtr/GeoNet @ {commit}",
        "versions": {
            "tensorflow": _version("tensorflow"),
            "tf_slim": _version("tf_slim"),
            "tf_keras": _version("tf_keras"),
        },
        "networks": {},
    }
    for key, (builder, opts, channels) in NETWORKS.items():
        graph = tf.Graph()
        with graph.as_default():
            opt = types.SimpleNamespace(**opts)
            inputs = tf.placeholder(tf.float32, [1, HEIGHT, WIDTH, channels])
            getattr(nets, builder)(opt, inputs)
            variables = tf.model_variables()
            out["networks"][key] = {
                "input_channels": channels,
                "variables": [[v.op.name, v.shape.as_list(), v.dtype.base_dtype.name] for v in variables],
            }
    # One variable per line: people review a mapping against this file as much as the tests read it.
    header = {k: v for k, v in out.items() if k != "networks"}
    lines = ["{" + json.dumps(header, indent=1)[1:-2] + ",", ' "networks": {']
    for n, (key, net) in enumerate(out["networks"].items()):
        lines.append(f'  "{key}": {{"input_channels": {net["input_channels"]}, "variables": [')
        lines.append(",\n".join("   " + json.dumps(var) for var in net["variables"]))
        lines.append("  ]}" + ("," if n < len(out["networks"]) - 1 else ""))
    lines.append(" }\n}")
    sys.stdout.write("\n".join(lines) + "\n")


def _version(module: str) -> str:
    from importlib.metadata import version

    return version(module.replace("_", "-"))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
