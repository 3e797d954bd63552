"""A model that changes under the same name or folder (issue 60, item 1): ``batch --resume`` redoes the
sequences it made, and says why; ``predict`` over its earlier folder writes the new model's outputs.

The "re-export" here changes one weight of the fp32 DepthNet of a copy of the bundled model (with onnx,
a test tool here) and records the file's new sha256 in the manifest, as ``python -m export --force``
or ``geonet-infer convert --force`` into the same folder do.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from geonet_infer.models import bundled_models
from tests.runtime.batch.test_batch import cli, make_sequences
from tests.runtime.core.test_hostile_model import rehash

onnx = pytest.importorskip("onnx")


def reexport(model: Path, factor: float) -> None:
    """Scale the first conv weight of depthnet.onnx by ``factor`` and record the new sha256."""
    from onnx import numpy_helper

    path = model / "depthnet.onnx"
    graph = onnx.load(str(path))
    init = next(i for i in graph.graph.initializer if len(i.dims) == 4)
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * np.float32(factor), init.name))
    onnx.save(graph, str(path))
    rehash(model, "depthnet.onnx")


@pytest.fixture
def model(tmp_path) -> Path:
    copy = tmp_path / "M"
    shutil.copytree(bundled_models()["small_synth"], copy)
    return copy


def _depths(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "depth").glob("*.npy"))}


def test_resume_after_the_model_changed_redoes_the_sequence(tmp_path, capfd, model):
    (seq,) = make_sequences(tmp_path / "in", ["seqA"], 3)
    out = tmp_path / "O"
    base = ["batch", seq, "--out", out, "--model", model, "--tasks", "depth", "--no-vis", "--no-progress"]
    assert cli(capfd, *base)[0] == 0
    first = _depths(out / "seqA")
    reexport(model, 1.5)
    rc, stdout, stderr = cli(capfd, *base, "--resume")
    assert rc == 0 and "0 skipped (complete already), 1 redone" in stdout, stdout
    assert "seqA: redoing it, the model changed since the run (fp32/depthnet differ)" in stderr, stderr
    again = _depths(out / "seqA")
    assert again != first
    fresh = tmp_path / "fresh"
    assert cli(capfd, "predict", seq, "--out", fresh, "--model", model, "--tasks", "depth", "--no-vis",
               "--no-progress")[0] == 0  # fmt: skip
    assert again == _depths(fresh)
    rc, stdout, _ = cli(capfd, *base, "--resume")  # the same model again: complete, skipped
    assert rc == 0 and "1 skipped" in stdout, stdout


def test_a_done_that_names_the_model_by_its_folder_is_redone(tmp_path, capfd, model):
    """Markers written before the graphs were recorded name the model's folder: redone, not refused."""
    (seq,) = make_sequences(tmp_path / "in", ["seqA"], 2)
    out = tmp_path / "O"
    base = ["batch", seq, "--out", out, "--model", model, "--tasks", "depth", "--no-vis", "--no-progress"]
    assert cli(capfd, *base)[0] == 0
    marker_path = out / "seqA" / ".done"
    marker = json.loads(marker_path.read_text())
    marker["options"].pop("graphs")
    marker["options"]["model"] = str(model)
    marker_path.write_text(json.dumps(marker))
    rc, _, stderr = cli(capfd, *base, "--resume")
    assert rc == 0 and "names the model by its folder, not by its graphs" in stderr, stderr


def test_predict_over_its_earlier_folder_writes_the_new_models_outputs(tmp_path, capfd, model):
    (seq,) = make_sequences(tmp_path / "in", ["seqA"], 3)
    out = tmp_path / "O"
    argv = ["predict", seq, "--out", out, "--model", model, "--tasks", "depth", "--no-vis", "--no-progress"]
    assert cli(capfd, *argv)[0] == 0
    first = _depths(out)
    reexport(model, 0.5)
    assert cli(capfd, *argv)[0] == 0
    fresh = tmp_path / "fresh"
    assert cli(capfd, *[fresh if a == out else a for a in argv])[0] == 0
    assert _depths(out) == _depths(fresh) != first
