"""The bundled model's graphs are the shipped weights' (issue 60, item 5): ``weights/small_synth.pt`` is the
checkpoint the manifest names by sha256, and exporting it again gives the bundled graphs' outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import geonet_infer
from geonet_infer.core.manifest import file_sha256, load_manifest
from geonet_infer.io import list_images
from geonet_infer.models import bundled_models
from geonet_infer.samples import SAMPLE_FRAMES

WEIGHTS = Path(__file__).resolve().parents[2] / "weights" / "small_synth.pt"


def test_the_manifest_names_the_shipped_weights_by_their_sha256():
    manifest = load_manifest(bundled_models()["small_synth"])
    assert manifest.provenance.checkpoint_sha256 == file_sha256(WEIGHTS)


def test_exporting_the_shipped_weights_again_gives_the_bundled_graphs_outputs(tmp_path):
    from export import ExportConfig, export_model

    bundled = bundled_models()["small_synth"]
    again = export_model(ExportConfig(out=tmp_path / "again", checkpoint=WEIGHTS, quiet=True))
    frames = list_images(SAMPLE_FRAMES)[:3]
    a, b = geonet_infer.load(bundled, precision="fp32"), geonet_infer.load(again, precision="fp32")
    np.testing.assert_allclose(b.depth(frames[0]).depth, a.depth(frames[0]).depth, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.pose(frames).vectors, a.pose(frames).vectors, atol=1e-6)
    K = np.array([[200.0, 0, 208], [0, 200.0, 64], [0, 0, 1]])
    np.testing.assert_allclose(b.flow(frames, K).flow, a.flow(frames, K).flow, atol=1e-4)
