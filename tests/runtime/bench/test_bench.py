"""`geonet-infer bench` and geonet_infer.engines.timing: JSON schema, every task, statistics, bad input.

Runs the bundled model with 2 timed calls per case, so it checks wiring, never speed: no
wall-clock threshold is asserted anywhere. int8 plumbing uses a model directory in tmp_path
whose int8 set points at the fp32 files (cheap; the numbers are fp32 ones, the code path is
the int8 one). No torch.
"""

from __future__ import annotations

import gc
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

import geonet_infer
from geonet_infer.bench.cases import BENCH_TASKS, MODES
from geonet_infer.cli import main
from geonet_infer.engines import timing

PKG = Path(geonet_infer.__file__).resolve().parent
MODEL_DIR = PKG / "models" / "small_synth"
FAST = ("--iters", "2", "--warmup", "1", "--rewarm-ms", "0", "--quiet")
ROW_KEYS = {
    "task",
    "mode",
    "precision",
    "backend",
    "batch",
    "p50_ms",
    "p90_ms",
    "p99_ms",
    "mean_ms",
    "std_ms",
    "min_ms",
    "max_ms",
    "fps",
    "n",
    "items_per_call",
    "per_item_p50_ms",
    "graphs",
    "unit",
}
ENV_KEYS = {
    "cpu",
    "cpu_flags",
    "usable_cpus",
    "threads",
    "python",
    "onnxruntime",
    "numpy",
    "opencv",
    "geonet_infer",
    "session_options",
    "model",
    "peak_rss_mib",
    "memory",
    "timing",
    "input_size",
    "load_average_start",
}


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main(["bench", *[str(a) for a in argv]])
    out, err = capsys.readouterr()
    return rc, out, err


def model_copy(tmp_path: Path, edit=None) -> Path:
    """The bundled model copied into tmp_path (graphs linked from outside it are refused), its manifest
    passed through ``edit``."""
    out = tmp_path / "model"
    shutil.copytree(MODEL_DIR, out)
    manifest = json.loads((MODEL_DIR / "manifest.json").read_text())
    if edit is not None:
        edit(manifest)
    (out / "manifest.json").write_text(json.dumps(manifest))
    return out


def fake_int8(manifest: dict) -> None:
    """An int8 set made of the fp32 files (plumbing only)."""
    manifest["graphs"]["int8"] = json.loads(json.dumps(manifest["graphs"]["fp32"]))
    manifest["precisions"] = ["fp32", "int8"]


def no_int8(manifest: dict) -> None:
    manifest["graphs"].pop("int8", None)
    manifest["precisions"] = ["fp32"]
    manifest["quantization"] = None


def no_resflownet(manifest: dict) -> None:
    for graphs in manifest["graphs"].values():
        graphs.pop("resflownet", None)


def check_row(row: dict) -> None:
    assert ROW_KEYS <= set(row), ROW_KEYS - set(row)
    assert row["backend"] == "onnxruntime"
    for key in ("p50_ms", "p90_ms", "p99_ms", "mean_ms", "min_ms", "max_ms", "fps", "per_item_p50_ms"):
        assert math.isfinite(row[key]) and row[key] > 0, (key, row)
    assert row["std_ms"] >= 0
    assert row["min_ms"] <= row["p50_ms"] <= row["p90_ms"] <= row["p99_ms"] <= row["max_ms"]
    assert row["min_ms"] <= row["mean_ms"] <= row["max_ms"]
    if row["task"] == "sequence":
        assert row["unit"] == "frame" and row["items_per_call"] == row["frames"] and row["pairs"] == row["frames"] - 1
        assert row["fps"] == pytest.approx(1000.0 / row["mean_ms"])
    else:
        assert row["unit"] == "call" and row["items_per_call"] == row["batch"]
        assert row["fps"] == pytest.approx(row["batch"] * 1000.0 / row["mean_ms"])


# ----------------------------------------------------------------------------- the bundled model
@pytest.fixture(scope="module")
def bundled_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    capsys_free = main(["bench", *FAST, "--precision", "fp32", "--seq-frames", "4", "--json", str(out)])
    return capsys_free, json.loads(out.read_text())


def test_json_holds_every_task_and_mode_for_fp32(bundled_run):
    rc, data = bundled_run
    assert rc == 0
    assert set(data) >= {"environment", "results"}
    rows = data["results"]
    assert {(r["task"], r["mode"]) for r in rows} == {(t, m) for t in BENCH_TASKS for m in MODES}
    assert len(rows) == len(BENCH_TASKS) * len(MODES)
    for row in rows:
        check_row(row)
        assert row["precision"] == "fp32" and row["batch"] == 1 and row["n"] == 2
    flow = next(r for r in rows if r["task"] == "flow")
    assert flow["graphs"] == ["depthnet", "posenet", "rigidflow", "resflownet"]


def test_environment_block(bundled_run):
    _, data = bundled_run
    env = data["environment"]
    assert ENV_KEYS <= set(env), ENV_KEYS - set(env)
    assert env["usable_cpus"] >= 1 and env["threads"] >= 1
    assert env["session_options"]["intra_op_num_threads"] == env["threads"]
    assert env["model"]["arch"] and isinstance(env["model"]["random_init"], bool)
    assert env["input_size"] == [1242, 375]
    assert env["timing"]["iters"] == 2 and env["timing"]["warmup"] == 1
    mem = env["memory"]["onnxruntime/fp32"]
    assert mem["graph_files_mib"] > 0 and mem["peak_rss_mib"] >= mem["rss_after_load_mib"] > 0
    assert env["peak_rss_mib"] >= mem["peak_rss_mib"]
    assert "INT8 kernel" in env["isa"]["line"] and env["isa"]["int8_kernel"]
    runs = {name: e["run"] for name, e in env["engines"]["onnxruntime/fp32"].items()}
    assert runs["depthnet"] == {"engine": "onnxruntime", "precision": "fp32", "why": "backend onnxruntime"}


def test_table_is_printed(capsys, tmp_path):
    rc, out, err = run_cli(
        capsys, *FAST, "--precision", "fp32", "--tasks", "pose", "--modes", "graph", "--input-size", "graph"
    )
    assert rc == 0, err
    assert "p50 ms" in out and "pose" in out and "416x128" in out


# ----------------------------------------------------------------------------- other model directories
def test_int8_set_and_batches(capsys, tmp_path):
    model = model_copy(tmp_path, fake_int8)
    out = tmp_path / "bench.json"
    rc, _, err = run_cli(
        capsys,
        *FAST,
        "--model",
        model,
        "--tasks",
        "depth,pose,sequence",
        "--batch",
        "1,2",
        "--seq-frames",
        "3",
        "--input-size",
        "graph",
        "--json",
        out,
    )
    assert rc == 0, err
    data = json.loads(out.read_text())
    got = {(r["task"], r["mode"], r["precision"], r["batch"]) for r in data["results"]}
    for precision in ("fp32", "int8"):  # the default: every precision the model has
        for batch in (1, 2):
            assert {("depth", m, precision, batch) for m in MODES} <= got
            assert {("sequence", m, precision, batch) for m in MODES} <= got
            assert ("pose", "graph", precision, batch) in got
        assert ("pose", "e2e", precision, 1) in got
        assert ("pose", "e2e", precision, 2) not in got  # Predictor.pose takes one snippet
        assert any(s["task"] == "pose" and s["batch"] == 2 and s["precision"] == precision for s in data["skipped"])
    for row in data["results"]:
        check_row(row)
    assert set(data["environment"]["memory"]) == {"onnxruntime/fp32", "onnxruntime/int8"}


def test_model_without_resflownet(capsys, tmp_path):
    model = model_copy(tmp_path, no_resflownet)
    rc, _, err = run_cli(capsys, *FAST, "--model", model, "--tasks", "resflow")
    assert rc == 2 and "resflownet" in err and len(err.strip().splitlines()) == 1
    out = tmp_path / "bench.json"
    rc, _, err = run_cli(
        capsys,
        "--iters",
        "1",
        "--warmup",
        "0",
        "--rewarm-ms",
        "0",
        "--quiet",
        "--model",
        model,
        "--modes",
        "graph",
        "--seq-frames",
        "2",
        "--input-size",
        "graph",
        "--json",
        out,
    )
    assert rc == 0, err
    data = json.loads(out.read_text())
    assert {r["task"] for r in data["results"]} == set(BENCH_TASKS) - {"resflow"}
    assert any(s["task"] == "resflow" for s in data["skipped"])
    flow = next(r for r in data["results"] if r["task"] == "flow")
    assert flow["graphs"] == ["depthnet", "posenet", "rigidflow"]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (("--tasks", "depth,optical"), "optical"),
        (("--precision", "fp16"), "fp16"),
        (("--backend", "tensorrt"), "tensorrt"),
        (("--iters", "0"), "--iters"),
        (("--warmup", "-1"), "--warmup"),
        (("--batch", "0"), "--batch"),
        (("--modes", "cold"), "cold"),
        (("--input-size", "big"), "--input-size"),
        (("--seq-frames", "1"), "--seq-frames"),
        (("--model", "no_such_model_dir"), "no_such_model_dir"),
    ],
    ids=["task", "precision", "backend", "iters", "warmup", "batch", "mode", "input-size", "seq-frames", "model"],
)
def test_bad_input_exits_2_with_one_line(capsys, argv, needle):
    rc, out, err = run_cli(capsys, *argv)
    assert rc == 2
    assert err.startswith("geonet-infer bench: error:") and needle in err
    assert len(err.strip().splitlines()) == 1


def test_int8_on_a_model_without_int8_exits_2(capsys, tmp_path):
    model = model_copy(tmp_path, no_int8)
    rc, _, err = run_cli(capsys, "--model", model, "--precision", "int8")
    assert rc == 2 and "int8" in err and "manifest.json" in err and len(err.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- geonet_infer.engines.timing
def test_summarize_matches_numpy():
    rng = np.random.default_rng(0)
    ns = rng.integers(1_000_000, 50_000_000, size=101)
    s = timing.summarize(ns, items_per_call=4)
    ms = ns / 1e6
    assert s.n == 101
    assert s.p50_ms == pytest.approx(np.median(ms))
    assert s.p90_ms == pytest.approx(np.percentile(ms, 90)) and s.p99_ms == pytest.approx(np.percentile(ms, 99))
    assert s.mean_ms == pytest.approx(ms.mean()) and s.std_ms == pytest.approx(ms.std(ddof=1))
    assert s.min_ms <= s.p50_ms <= s.p90_ms <= s.p99_ms <= s.max_ms
    assert s.fps == pytest.approx(4 * 1000 / ms.mean())
    per = s.scaled(0.25)
    assert per.p50_ms == pytest.approx(s.p50_ms / 4) and per.fps == s.fps
    one = timing.summarize([2_000_000])
    assert one.std_ms == 0 and one.p50_ms == one.p99_ms == 2.0
    with pytest.raises(ValueError):
        timing.summarize([])


def test_time_interleaved_counts_calls_and_restores_gc():
    calls = {"a": 0, "b": 0}
    order = []

    def make(name):
        def fn():
            calls[name] += 1
            order.append(name)

        return fn

    cases = [timing.Case("a", make("a")), timing.Case("b", make("b"), items_per_call=3)]
    assert gc.isenabled()
    timing.time_interleaved(cases, warmup=2, iters=5, block=2, quiet=False, rewarm_ms=0)
    assert gc.isenabled()
    assert [len(c.samples_ns) for c in cases] == [5, 5]
    assert calls == {"a": 7, "b": 7}
    # rounds rotate the order: round 1 starts with a, round 2 with b
    timed = order[4:]
    assert timed[:4] == ["a", "a", "b", "b"] and timed[4:8] == ["b", "b", "a", "a"]
    assert cases[1].stats().items_per_call == 3
    with pytest.raises(ValueError):
        timing.time_interleaved(cases, iters=0)
    stats = timing.measure(lambda: None, warmup=0, iters=3)
    assert stats.n == 3


def test_memory_helpers():
    assert timing.peak_rss_mib() > 0
    rss = timing.current_rss_mib()
    assert rss is None or 0 < rss <= timing.peak_rss_mib() + 1
    assert timing.wait_quiet(timeout_ms=50) >= 0
