"""What the bundled model is, said where users meet it (issue 33).

The manifest's ``model_card`` (written by ``benchmarks.model_card`` from the card's measurement)
makes ``predict`` and ``batch`` print one line for a model trained on synthetic scenes only or no
better than its baseline on real data (the bundled one: worse than a constant depth) and record it in
summary.json, ``info`` show the scores or "not measured", and ``demo --real`` draw the real
KITTI frame. Golden numbers come from the card's own record (docs/models.json), never from the
runtime under test; a copy of the bundled model with ``model_card`` removed is "an export without
scores" (export writes none), and it keeps the bundled name, so detection by name would show.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import pytest

import geonet_infer
from geonet_infer.cli import demo as demo_cli
from geonet_infer.cli import main
from geonet_infer.models.manifest import MANIFEST_NAME, file_sha256
from tests.runtime.cli.test_cli import sample_folder

ROOT = Path(__file__).resolve().parents[3]
PKG = Path(geonet_infer.__file__).resolve().parent
MODEL_DIR = PKG / "models" / "small_synth"
CARD_JSON = ROOT / "docs" / "models.json"
NOTICE = "on real video it is"


@pytest.fixture(scope="module")
def card() -> dict:
    """The card's recorded measurement (docs/models.json)."""
    if not CARD_JSON.is_file():
        pytest.skip("docs/models.json is not here (runtime-only checkout)")
    return json.loads(CARD_JSON.read_text())


@pytest.fixture(scope="module")
def unscored(tmp_path_factory) -> Path:
    """The bundled model directory, copied, with ``model_card`` removed from its manifest."""
    out = tmp_path_factory.mktemp("unscored") / "small_synth"
    shutil.copytree(MODEL_DIR, out)
    raw = json.loads((out / MANIFEST_NAME).read_text())
    raw.pop("model_card", None)
    (out / MANIFEST_NAME).write_text(json.dumps(raw, indent=2) + "\n")
    return out


def notice_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if NOTICE in line]


def check_notice(line: str, card: dict) -> None:
    """The card's real-data depth AbsRel and its constant-depth baseline, and where a real-video model is."""
    depth = card["kitti"]["depth"]
    model, constant = depth["fp32"]["abs_rel"], depth["constant_baseline"]["abs_rel"]
    assert model >= constant, "the bundled model beats a constant depth now: these tests expect a notice"
    for number in (model, constant):
        assert f"{number:.3g}" in line
    assert "worse than the constant depth baseline" in line
    assert ("trained on synthetic scenes only" in line) == (not card.get("real_training"))
    assert "docs/models.md" in line and "docs/official_models.md" in line and "geonet-infer convert" in line


# ----------------------------------------------------------------------------- predict
def test_predict_prints_the_notice_once_and_records_it_quiet_keeps_the_field(tmp_path, capsys, card):
    src = sample_folder(tmp_path, 3)
    assert main(["predict", str(src), "--out", str(tmp_path / "a"), "--tasks", "depth", "--no-progress"]) == 0
    lines = notice_lines(capsys.readouterr().err)
    assert len(lines) == 1
    check_notice(lines[0], card)
    field = json.loads((tmp_path / "a" / "summary.json").read_text())["model_notice"]
    assert field and field in lines[0]

    argv = ["predict", str(src), "--out", str(tmp_path / "q"), "--tasks", "depth", "--no-progress", "--quiet"]
    assert main(argv) == 0
    assert notice_lines(capsys.readouterr().err) == []
    assert json.loads((tmp_path / "q" / "summary.json").read_text())["model_notice"] == field


def test_predict_on_a_model_without_scores_says_nothing(tmp_path, capsys, unscored):
    src = sample_folder(tmp_path, 3)
    argv = ["predict", str(src), "--out", str(tmp_path / "o"), "--model", str(unscored), "--tasks", "depth"]
    assert main([*argv, "--no-progress"]) == 0
    assert notice_lines(capsys.readouterr().err) == []
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["model_notice"] is None


# ----------------------------------------------------------------------------- batch
def test_batch_prints_the_notice_and_records_it_quiet_keeps_the_field(tmp_path, capsys, card):
    src = sample_folder(tmp_path, 3)
    common = ["--tasks", "depth", "--workers", "1", "--no-progress"]
    assert main(["batch", str(src), "--out", str(tmp_path / "a"), *common]) == 0
    lines = notice_lines(capsys.readouterr().err)
    assert len(lines) == 1
    check_notice(lines[0], card)
    field = json.loads((tmp_path / "a" / "summary.json").read_text())["model_notice"]
    assert field and field in lines[0]
    assert main(["batch", str(src), "--out", str(tmp_path / "q"), *common, "--quiet"]) == 0
    assert notice_lines(capsys.readouterr().err) == []
    assert json.loads((tmp_path / "q" / "summary.json").read_text())["model_notice"] == field


# ----------------------------------------------------------------------------- info
def test_info_shows_what_the_model_was_trained_on_and_its_scores(capsys, card):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    real = [line for line in out.splitlines() if "real-data score" in line]
    assert len(real) == 1 and f"{card['kitti']['depth']['fp32']['abs_rel']:.3g}" in real[0] and "worse" in real[0]
    if card.get("real_training"):
        assert f"trained on: synthetic scenes made by training.synth, then {card['real_training']}" in out
    else:
        assert f"trained on: synthetic scenes only ({card['model']['provenance']['data_dir']})" in out
    synth = [line for line in out.splitlines() if "synthetic score" in line]
    assert len(synth) == 3 and f"{card['synthetic']['depth']['fp32']['abs_rel']:.3g}" in synth[0]
    assert main(["info", "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)["model"]["model_card"]
    assert scores["real"][0]["value"] == card["kitti"]["depth"]["fp32"]["abs_rel"]
    assert scores["real"][0]["baseline_value"] == card["kitti"]["depth"]["constant_baseline"]["abs_rel"]


def test_info_on_an_export_without_scores_says_not_measured(capsys, unscored):
    assert main(["info", "--model", str(unscored)]) == 0
    out = capsys.readouterr().out
    assert "real-data scores: not measured" in out and "synthetic scores: not measured" in out
    assert main(["info", "--model", str(unscored), "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)["model"]["model_card"]
    assert scores["real"] == scores["synthetic"] == "not measured"


# ----------------------------------------------------------------------------- the card writes the manifest
def test_card_from_json_writes_the_manifest_scores_and_renders_the_same_card(
    tmp_path, capsys, monkeypatch, card, unscored
):
    pytest.importorskip("benchmarks.model_card")
    from benchmarks.model_card.cli import main as card_main

    model = tmp_path / "small_synth"
    shutil.copytree(unscored, model)
    graphs = {p.relative_to(model): file_sha256(p) for p in model.rglob("*.onnx")}
    monkeypatch.chdir(tmp_path)  # --out as in the card's own command: the manifest records where the card is
    (tmp_path / "docs").mkdir()
    out = Path("docs") / "models.md"
    argv = ["--model", str(model), "--out", str(out), "--json", str(tmp_path / "m.json")]
    assert card_main([*argv, "--from-json", str(CARD_JSON), "--quiet"]) == 0
    written = json.loads((model / MANIFEST_NAME).read_text())["model_card"]
    assert written["real"][0]["value"] == card["kitti"]["depth"]["fp32"]["abs_rel"]
    assert written["synthetic"][0]["value"] == card["synthetic"]["depth"]["fp32"]["abs_rel"]
    assert written["synthetic_only"] is (not card.get("real_training"))
    assert {p.relative_to(model): file_sha256(p) for p in model.rglob("*.onnx")} == graphs
    # same numbers and same manifest content as the bundled model: the card renders as docs/models.md
    assert out.read_text() == (ROOT / "docs" / "models.md").read_text()
    assert main(["info", "--model", str(model)]) == 0 and "real-data score: depth AbsRel" in capsys.readouterr().out


def test_card_from_json_refuses_numbers_of_other_graphs(tmp_path, capsys, card, unscored):
    pytest.importorskip("benchmarks.model_card")
    from benchmarks.model_card.cli import main as card_main

    other = dict(card, model=dict(card["model"], files=[dict(f, sha256="0" * 64) for f in card["model"]["files"]]))
    (tmp_path / "other.json").write_text(json.dumps(other))
    before = (unscored / MANIFEST_NAME).read_bytes()
    argv = ["--model", str(unscored), "--out", str(tmp_path / "m.md"), "--from-json", str(tmp_path / "other.json")]
    assert card_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other.json" in err[0] and "other graph files" in err[0]
    assert (unscored / MANIFEST_NAME).read_bytes() == before and not (tmp_path / "m.md").exists()


# ----------------------------------------------------------------------------- demo --real
def test_demo_real_draws_the_real_kitti_frame(tmp_path, capsys, realdata):
    out = tmp_path / "real"
    assert main(["demo", "--real", "--out", str(out), "--no-progress"]) == 0
    img = cv2.imread(str(out / "demo.png"))
    strip = img.shape[0] - demo_cli.REAL_PANEL_HEIGHT  # the label strip above the panels
    assert 0 < strip < 40 and img.shape[1] > 10 * img.shape[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == demo_cli.REAL_FRAMES and summary["input"]["kind"] == "kitti_drive"
    assert summary["image_size"] == [1242, 375]  # KITTI raw colour frames (../shared/realdata/README.md)
    assert NOTICE in summary["model_notice"]


def test_demo_real_without_the_shared_data_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(demo_cli, "REAL_DRIVE", Path("no_such_shared") / "realdata" / "drive")
    assert main(["demo", "--real", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_shared" in err[0] and "../shared/realdata" in err[0]
    assert not (tmp_path / "o").exists()


def test_a_malformed_model_card_is_one_line_exit_2(tmp_path, capsys, unscored):
    model = tmp_path / "small_synth"
    shutil.copytree(unscored, model)
    raw = json.loads((model / MANIFEST_NAME).read_text())
    raw["model_card"] = {"trained_on": "x", "synthetic_only": True, "measured_in": "x", "generated_utc": "x"}
    raw["model_card"]["real"] = [{"task": "depth", "metric": "AbsRel", "data": "x", "value": "NaN"}]
    (model / MANIFEST_NAME).write_text(json.dumps(raw))
    assert main(["info", "--model", str(model)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(model / MANIFEST_NAME) in err[0] and "invalid manifest" in err[0]


def test_the_notice_is_for_synthetic_only_models_and_models_no_better_than_their_real_baseline():
    from geonet_infer.models.manifest import ModelCard

    def card(synthetic_only: bool, value: float) -> ModelCard:
        real = {"task": "depth", "metric": "AbsRel", "data": "KITTI", "value": value, "baseline": "constant depth",
                "baseline_value": 0.376}  # fmt: skip
        return ModelCard.from_dict({"trained_on": "x", "synthetic_only": synthetic_only, "measured_in": "card.md",
                                    "generated_utc": "now", "real": [real]})  # fmt: skip

    assert card(False, 0.2).notice() is None  # trained on real footage too and better than constant depth
    worse = card(False, 0.38).notice()
    assert worse and "worse than the constant depth baseline: depth AbsRel 0.38 vs 0.376" in worse
    assert "synthetic scenes only" not in worse and "geonet-infer convert" in worse
    better = card(True, 0.2).notice()
    assert better and better.startswith("trained on synthetic scenes only: on real video it is better")
