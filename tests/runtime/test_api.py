"""The public API's contracts from issue 29: one camera keyword, frozen results, one error family,
and registries that a new engine or evaluation layout joins with one entry."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

import geonet_infer
from geonet_infer import BackendUnavailableError, GeoNetError, GeoNetInputError, InputError, ModelError
from geonet_infer.cli import main
from geonet_infer.engines import ENGINES
from geonet_infer.eval import datasets
from geonet_infer.eval.datasets import DepthItem, Found, Layout
from geonet_infer.io import list_images, read_camera, read_image
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES


@pytest.fixture(scope="module")
def predictor():
    return geonet_infer.load()


@pytest.fixture(scope="module")
def frames():
    return [read_image(p) for p in list_images(SAMPLE_FRAMES)[:4]]


def test_error_family():
    for cls in (InputError, ModelError, BackendUnavailableError):
        assert issubclass(cls, GeoNetError) and issubclass(cls, ValueError)
    assert GeoNetInputError is GeoNetError  # the 0.x name still catches every one of them
    err = ModelError("/models/x", "no manifest", "re-export it")
    assert str(err) == "/models/x: no manifest. re-export it"


def test_a_missing_model_is_a_model_error(tmp_path):
    with pytest.raises(ModelError, match="no such model directory"):
        geonet_infer.load(tmp_path / "nowhere")


def test_bad_arguments_are_input_errors(predictor, frames):
    with pytest.raises(InputError, match="unknown task"):
        predictor.iter_sequence(frames, read_camera(SAMPLE_CALIB), tasks=("depth", "mesh"))
    with pytest.raises(InputError, match="3x3"):
        predictor.flow(frames[:3], np.eye(2))


def test_the_deprecated_K_keyword_warns_and_gives_the_same_flow(predictor, frames):
    camera = read_camera(SAMPLE_CALIB)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # camera= is the keyword: no warning
        new = predictor.flow(frames[:3], camera=camera)
    with pytest.warns(DeprecationWarning, match="camera="):
        old = predictor.flow(frames[:3], K=camera)
    np.testing.assert_array_equal(new.flow, old.flow)
    with pytest.warns(DeprecationWarning):
        seq = predictor.predict_sequence(frames, K=camera)
    np.testing.assert_array_equal(seq.depth, predictor.predict_sequence(frames, camera).depth)
    with pytest.raises(InputError, match="both camera= and K="):
        predictor.flow(frames[:3], camera, K=camera)


def test_results_are_frozen(predictor, frames):
    result = predictor.depth(frames[0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.depth = np.zeros(1)  # type: ignore[misc]
    frame = next(predictor.iter_sequence(frames, read_camera(SAMPLE_CALIB), tasks=("depth",)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        frame.metric_scale = 2.0  # type: ignore[misc]


def test_depth_alone_runs_on_a_single_frame(predictor, frames):
    """Depth-only sequences (what `predict --tasks depth` streams) need no pair."""
    (only,) = predictor.iter_sequence(frames[:1], None, tasks=("depth",))
    np.testing.assert_array_equal(only.depth, predictor.depth(frames[0]).depth)


def test_an_engine_that_is_not_installed_is_named_with_its_install_hint(monkeypatch, capfd):
    optional = [cls for cls in ENGINES.values() if cls is not next(iter(ENGINES.values()))]
    assert optional, "a second engine is registered (OpenVINO)"
    engine = optional[0]
    monkeypatch.setattr(engine, "available", staticmethod(lambda: False))
    rc = main(["bench", "--backend", engine.name, "--iters", "1", "--warmup", "0", "--quiet"])
    err = capfd.readouterr().err
    assert rc == 2 and f"--backend {engine.name} needs {engine.requires}" in err and engine.install_hint in err


class _MarkerLayout(Layout):
    """A layout added the documented way: one class, one registry entry."""

    name = "marker"
    tasks = ("depth",)
    depth_crop = "eigen"
    help = {"depth": ("a folder with MARKER and image.png + depth.png",)}

    @staticmethod
    def detect(task: str, root: Path) -> bool:
        return (root / "MARKER").is_file()

    @classmethod
    def items(cls, task, root, *, sequences, stride, multiview) -> Found:
        return Found([DepthItem("one", root / "image.png", root / "depth.png", "png")], "marker test set")


def test_a_new_layout_is_one_class_and_one_registry_entry(tmp_path, monkeypatch):
    monkeypatch.setitem(datasets.REGISTRY, _MarkerLayout.name, _MarkerLayout)
    (tmp_path / "MARKER").write_text("")
    assert datasets.detect_layout("depth", tmp_path) == "marker"
    data = datasets.load_dataset("depth", tmp_path)
    assert data.layout == "marker" and [item.name for item in data.items] == ["one"]
    assert datasets.layout_class("marker").depth_crop == "eigen"
    with pytest.raises(InputError, match="unknown flow layout 'marker'"):
        datasets.load_dataset("flow", tmp_path, "marker")
    # a layout without intrinsics says so instead of assuming a KITTI folder
    with pytest.raises(InputError, match="the marker layout has no camera intrinsics"):
        _MarkerLayout.depth_intrinsics(data.items[0])


def test_the_eval_cli_offers_every_registered_layout():
    from geonet_infer.cli import eval as eval_cli

    for name in datasets.REGISTRY:
        assert f" {name} " in eval_cli.HELP
