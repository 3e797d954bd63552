"""``kitti-disparity``: KITTI 2015 stereo disparity ground truth as depth.

``[training/]image_2/NNNNNN_10.png`` with ``disp_occ_0/NNNNNN_10.png`` (every pixel with data;
``disp_noc_0/`` where ``disp_occ_0/`` is absent): 16-bit PNG, disparity = value / 256 px, 0 = no
data. Depth = fx · baseline / disparity. fx and the baseline come from the scene's
``calib_cam_to_cam/NNNNNN.txt`` (``P_rect_02``, ``P_rect_03``) where the folder has it; options
``fx`` and ``baseline`` (``--fx``, ``--baseline``) give them otherwise, or override the file.
KITTI's stereo baseline is 0.54 m; fx is 707.09–721.54 px depending on the recording day. The
dataset's notes and ``details`` say which values were used and where they came from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.eval.datasets.base import (
    DepthItem,
    Found,
    Layout,
    benchmark_root,
    calibration_K_or_error,
)
from geonet_infer.eval.stereo import focal_and_baseline

GT_FOLDERS = ("disp_occ_0", "disp_noc_0")  # preference order: occ has every pixel with data
CALIB_FOLDER = "calib_cam_to_cam"
KITTI_BASELINE_M = 0.54  # KITTI's documented stereo baseline (the calibrations give 0.532-0.537 m)


def _root(root: Path) -> tuple[Path, str] | None:
    """(benchmark folder, GT folder name) of ``root`` or its ``training/``, or None."""
    for gt in GT_FOLDERS:
        base = benchmark_root(root, "image_2", gt)
        if base is not None:
            return base, gt
    return None


def _positive(value: float | None, flag: str) -> float | None:
    if value is not None and not (np.isfinite(value) and value > 0):
        raise InputError(None, f"{flag} {value:g} must be a positive number")
    return value


class KittiDisparity(Layout):
    name = "kitti-disparity"
    help = {  # geonet-infer eval --help: one entry per task, one string per line
        "depth": (
            "KITTI 2015 stereo: [training/]image_2/NNNNNN_10.png + disp_occ_0/ (or",
            "disp_noc_0/); depth = fx·baseline/disparity, fx and baseline from",
            "calib_cam_to_cam/NNNNNN.txt or --fx PX --baseline M (KITTI: 0.54 m)",
        ),
    }
    tasks = ("depth",)
    depth_crop = "garg"  # KITTI's camera 2 at full resolution, as the raw drives
    options = ("fx", "baseline")

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return _root(root) is not None

    @classmethod
    def items(
        cls,
        task: str,
        root: Path,
        *,
        sequences: list[str] | None,
        stride: int,
        multiview: Path | None,
        fx: float | None = None,
        baseline: float | None = None,
    ) -> Found:
        found = _root(root)
        if found is None:
            raise InputError(
                root / GT_FOLDERS[0],
                "KITTI 2015 disparity layout not found: need image_2/ and disp_occ_0/ or disp_noc_0/ "
                "(here or in training/)",
                "pass the stereo benchmark folder or its training/ folder",
            )
        base, gt_name = found
        fx, baseline = _positive(fx, "--fx"), _positive(baseline, "--baseline")
        gts = sorted((base / gt_name).glob("*.png"))
        if not gts:
            raise InputError(base / gt_name, "no disparity PNG here", "KITTI 2015 names them NNNNNN_10.png")
        items: list[DepthItem] = []
        used: list[dict] = []
        for gt in gts[::stride]:
            image = base / "image_2" / gt.name
            if not image.is_file():
                raise InputError(image, f"left image of {gt_name}/{gt.name} not found", "image_2/ holds the frames")
            calib = base / CALIB_FOLDER / f"{gt.name.split('_')[0]}.txt"
            file_fx = file_baseline = None
            if calib.is_file() and (fx is None or baseline is None):
                file_fx, file_baseline = focal_and_baseline(calib, "P_rect_02", "P_rect_03")
            use_fx = fx if fx is not None else file_fx
            use_baseline = baseline if baseline is not None else file_baseline
            if use_fx is None or use_baseline is None:
                missing = " and ".join(f for f, v in (("--fx", use_fx), ("--baseline", use_baseline)) if v is None)
                raise InputError(
                    calib,
                    f"no calibration for {gt_name}/{gt.name}: depth = fx·baseline/disparity needs fx and the baseline",
                    f"pass {missing} (KITTI: --baseline {KITTI_BASELINE_M:g}; fx is 707.09-721.54 px "
                    "depending on the recording day, 721.5377 on 2011_09_26)",
                )
            source = {
                "fx": "--fx" if fx is not None else f"{CALIB_FOLDER}/{calib.name} (P_rect_02)",
                "baseline": "--baseline"
                if baseline is not None
                else f"{CALIB_FOLDER}/{calib.name} (P_rect_02, P_rect_03)",
            }
            used.append({"frame": gt.stem, "fx": use_fx, "baseline_m": use_baseline, "source": source})
            items.append(DepthItem(gt.stem, image, gt, "disparity", calib=calib, fx_baseline=use_fx * use_baseline))
        notes = [_used_note(used, gt_name)]
        if any(u["source"]["fx"] == "--fx" and (base / CALIB_FOLDER).is_dir() for u in used):
            notes.append(f"--fx/--baseline override {CALIB_FOLDER}/ where given")
        desc = f"KITTI 2015 stereo {root.name}, {gt_name} disparity as depth"
        return Found(items, desc, notes, details={"ground_truth": gt_name, "disparity_to_depth": used})

    @classmethod
    def depth_intrinsics(cls, item: DepthItem) -> np.ndarray:
        """``P_rect_02`` of the scene's ``calib_cam_to_cam/NNNNNN.txt`` (InputError naming it when absent)."""
        assert item.calib is not None  # items() always sets the scene's calibration path
        return calibration_K_or_error(item.calib)


def _used_note(used: list[dict], gt_name: str) -> str:
    """One line: the fx and baseline of depth = fx·B/d, and where each came from."""
    fxs = sorted({u["fx"] for u in used})
    baselines = sorted({u["baseline_m"] for u in used})
    sources = sorted({f"fx from {u['source']['fx']}, baseline from {u['source']['baseline']}" for u in used})
    fx_text = f"{fxs[0]:.7g} px" if len(fxs) == 1 else f"{fxs[0]:.7g}–{fxs[-1]:.7g} px"
    b_text = f"{baselines[0]:.4g} m" if len(baselines) == 1 else f"{baselines[0]:.4g}–{baselines[-1]:.4g} m"
    where = sources[0] if len(sources) == 1 else f"{len(sources)} sources, see the JSON's data.details"
    return f"{gt_name}: depth = fx·baseline/disparity with fx {fx_text}, baseline {b_text} ({where})"
