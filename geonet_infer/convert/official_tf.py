"""The official GeoNet forward pass in TensorFlow, from a checkpoint's tensors (needs the ``[tf]`` extra).

``geonet_nets.py`` (yzcjtr/GeoNet @ 5b17602) re-stated with TF2 ops, NHWC: its padding (``tf.pad``
then VALID), nearest-neighbour resizing, slim's layer naming (``Conv``, ``Conv_1``, ... in creation
order) and BatchNorm without gamma, eps 1e-3. Used by ``python -m export --from-tf ... --verify``
when TensorFlow is installed, and by tests/export/test_from_tf.py, whose subclass creates random
variables as the layers are built.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

BN_EPS = np.float32(1e-3)  # slim's batch_norm default, which the official code keeps


def layer_name(index: int) -> str:
    """slim's auto-name of the ``index``-th unnamed conv of a scope."""
    return "Conv" if index == 0 else f"Conv_{index}"


def import_tf():
    """TensorFlow without its C++ start-up notices (CPU features, oneDNN, no CUDA)."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    import tensorflow as tf

    tf.get_logger().setLevel("ERROR")  # deprecation notes of the compat.v1 resize the official code used
    return tf


class OfficialNet:
    """One official network scope (``depth_net``, ``pose_net``, ``flow_net``) over ``values``
    (variable name -> array, as the checkpoint holds them). Layer calls take the next slim name."""

    def __init__(self, scope: str, values: Mapping[str, np.ndarray] | None = None):
        self.tf = import_tf()
        self.scope = scope
        self.values: dict[str, np.ndarray] = dict(values or {})
        self.index = 0

    # Where a layer's variables come from; tests/export/test_from_tf.py overrides these to create them.
    def weights(self, name: str, shape: tuple[int, int, int, int]) -> np.ndarray:
        return self.values[f"{name}/weights"]

    def batch_norm(self, name: str, y, out: int, var_scale: float) -> dict[str, np.ndarray]:
        return {tail: self.values[f"{name}/BatchNorm/{tail}"] for tail in ("beta", "moving_mean", "moving_variance")}

    def biases(self, name: str, out: int) -> np.ndarray:
        return self.values[f"{name}/biases"]

    def layer(self, x, out, k, stride, padding, bn=True, act="relu", var_scale=1.0):
        tf = self.tf
        name = f"{self.scope}/{layer_name(self.index)}"
        self.index += 1
        w = self.weights(name, (k, k, int(x.shape[-1]), out))
        if padding == "symmetric":  # the official `conv` helper: tf.pad p = floor((k-1)/2), then VALID
            p = (k - 1) // 2
            x = tf.pad(x, [[0, 0], [p, p], [p, p], [0, 0]])
            padding = "VALID"
        y = tf.nn.conv2d(x, w, stride, padding)
        if bn:
            stats = self.batch_norm(name, y, out, var_scale)
            y = (y - stats["moving_mean"]) / np.sqrt(stats["moving_variance"] + BN_EPS) + stats["beta"]
        else:
            y = y + self.biases(name, out)
        if act == "relu":
            return tf.nn.relu(y)
        return tf.sigmoid(y) if act == "sigmoid" else y

    # official helpers
    def conv(self, x, out, k, stride, bn=True, act="relu", var_scale=1.0):
        return self.layer(x, out, k, stride, "symmetric", bn, act, var_scale)

    def upconv(self, x, out):
        return self.conv(self.upsample_nn(x), out, 3, 1)

    def upsample_nn(self, x):
        return self.tf.compat.v1.image.resize_nearest_neighbor(x, [int(x.shape[1]) * 2, int(x.shape[2]) * 2])

    def resize_like(self, x, ref):
        if x.shape[1:3] == ref.shape[1:3]:
            return x
        return self.tf.compat.v1.image.resize_nearest_neighbor(x, [int(ref.shape[1]), int(ref.shape[2])])

    def resconv(self, x, n, stride):
        # var_scale: only for randomly created variables (the residual branch's BN variance x64, see
        # tests/export/test_from_tf.py); a checkpoint's own statistics are used as they are.
        out = self.conv(self.conv(self.conv(x, n, 1, 1), n, 3, stride), 4 * n, 1, 1, act=None, var_scale=64.0)
        return self.tf.nn.relu(out + self.conv(x, 4 * n, 1, stride, act=None))  # the always-taken projection

    def resnet50(self, x, get_pred):
        tf = self.tf
        conv1 = self.conv(x, 64, 7, 2)
        pool1 = tf.nn.max_pool2d(tf.pad(conv1, [[0, 0], [1, 1], [1, 1], [0, 0]]), 3, 2, "VALID")
        skips, out = [conv1, pool1], pool1
        for n, blocks in ((64, 3), (128, 4), (256, 6), (512, 3)):
            for _ in range(blocks - 1):
                out = self.resconv(out, n, 1)
            out = self.resconv(out, n, 2)
            skips.append(out)
        x, (skip1, skip2, skip3, skip4, skip5) = skips[-1], skips[:5]
        for n, skip in ((512, skip5), (256, skip4), (128, skip3)):
            up = self.resize_like(self.upconv(x, n), skip)
            x = self.conv(tf.concat([up, skip], 3), n, 3, 1)
        preds = [get_pred(x)]
        for n, skip in ((64, skip2), (32, skip1), (16, None)):
            parts = [self.upconv(x, n)] + ([skip] if skip is not None else []) + [self.upsample_nn(preds[-1])]
            x = self.conv(tf.concat(parts, 3), n, 3, 1)
            preds.append(get_pred(x))
        return preds[::-1]

    def disp_resnet50(self, image):
        """Disparity at 4 scales, finest first: 5*sigmoid + 0.01 (DISP_SCALING_RESNET50, MIN_DISP)."""
        return self.resnet50(image, lambda x: 5 * self.conv(x, 1, 3, 1, bn=False, act="sigmoid") + 0.01)

    def flow(self, flow_input):
        return self.resnet50(flow_input, lambda x: 0.1 * self.layer(x, 2, 3, 1, "SAME", bn=False, act=None))

    def pose(self, snippet, num_source):
        x = snippet
        for out, k in ((16, 7), (32, 5), (64, 3), (128, 3), (256, 3), (256, 3), (256, 3)):
            x = self.layer(x, out, k, 2, "SAME")
        pred = self.layer(x, 6 * num_source, 1, 1, "SAME", bn=False, act=None)
        return 0.01 * self.tf.reshape(self.tf.reduce_mean(pred, [1, 2]), [-1, num_source, 6])
