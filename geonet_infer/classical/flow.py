"""DIS optical flow (Kroeger et al. ECCV16, OpenCV) on grey frames: ``--flow-method dis`` and the eval's baseline."""

from __future__ import annotations

import cv2
import numpy as np

from geonet_infer.errors import InputError

DIS_PRESETS = {"medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def dis_flow(preset: str):
    """OpenCV DIS optical flow (Kroeger et al. ECCV16) with one of :data:`DIS_PRESETS`, on grey frames."""
    code = DIS_PRESETS[preset]

    def predict(frames: list, K=None) -> np.ndarray:
        dis = cv2.DISOpticalFlow.create(code)  # per call: the object keeps no useful state between pairs
        a, b = grey(frames[-2]), grey(frames[-1])
        try:
            return dis.calc(a, b, None)
        except cv2.error:  # its image pyramid: a frame under 16 px high at a wide aspect resizes to nothing
            raise InputError(
                None,
                f"DIS optical flow cannot run on {a.shape[1]}x{a.shape[0]} frames (too thin for its image pyramid)",
                "use --flow-method network, or frames at least 16 pixels high",
            ) from None

    return predict
