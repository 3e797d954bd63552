"""The record of the machine and model a measurement ran on: ``geonet-infer info`` and every bench JSON."""

from __future__ import annotations

import os
import platform
import subprocess
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer import __version__
from geonet_infer.core.predictor import TASK_GRAPHS as MODEL_TASK_GRAPHS  # depth, pose, flow
from geonet_infer.core.predictor import missing_graphs
from geonet_infer.engines import ENGINES, check_graphs, usable_cpus
from geonet_infer.engines.cpu import cpu_info, isa_line, proc_flags
from geonet_infer.models import bundled_models, resolve_model
from geonet_infer.models.manifest import ModelCard, load_manifest

CPU_FLAGS = (
    "avx2",
    "fma",
    "avx512f",
    "avx512bw",
    "avx512_vnni",
    "avx_vnni",
    "avx512_bf16",
    "amx_tile",
    "amx_int8",
    "amx_bf16",
)
THREAD_ENV = (
    "ORT_INTRA_OP_NUM_THREADS",
    "ORT_INTER_OP_NUM_THREADS",
    "OMP_NUM_THREADS",
    "OMP_WAIT_POLICY",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
)


def cpu_flags() -> list[str]:
    have = proc_flags()
    return [f for f in CPU_FLAGS if f in have]


def cpu_model() -> str:
    return cpu_info()["model"] or platform.machine()


@dataclass(frozen=True)
class Environment:
    """The software and machine a measurement ran on (``geonet-infer info``, every bench JSON)."""

    geonet_infer: str
    python: str
    engines: dict[str, str | None]  # engine name -> its package's version (None: not installed)
    numpy: str
    opencv: str
    providers: list[str]  # onnxruntime execution providers
    platform: str
    cpu: str
    isa: dict  # geonet_infer.engines.cpu.cpu_info(): the x86 features INT8 depends on, and the INT8 kernel
    usable_cpus: int  # affinity mask and cgroup quota (geonet_infer.engines.usable_cpus)
    default_threads: int  # threads per graph when none are given
    bundled_models: list[str]

    @classmethod
    def current(cls) -> Environment:
        import onnxruntime as ort

        cpus = usable_cpus()
        return cls(
            geonet_infer=__version__,
            python=platform.python_version(),
            engines={name: engine.version() for name, engine in ENGINES.items()},
            numpy=np.__version__,
            opencv=cv2.__version__,
            providers=ort.get_available_providers(),
            platform=platform.platform(),
            cpu=cpu_model(),
            isa={**cpu_info(), "line": isa_line()},
            usable_cpus=cpus,
            default_threads=cpus,
            bundled_models=list(bundled_models()),
        )

    def as_dict(self) -> dict:
        """The JSON record: the engines' versions as top-level keys, after "python"."""
        record = asdict(self)
        engines = record.pop("engines")
        keys = list(record)
        at = keys.index("python") + 1
        return {**{k: record[k] for k in keys[:at]}, **engines, **{k: record[k] for k in keys[at:]}}


def thread_env() -> dict[str, str | None]:
    """The environment variables that change thread counts behind our back."""
    return {k: os.environ.get(k) for k in THREAD_ENV}


def model_summary(model) -> dict:
    manifest = load_manifest(resolve_model(model))
    check_graphs(manifest)  # what the Predictor would refuse at load, info refuses too
    graphs = {
        p: {
            name: {
                "file": g.file,
                "sha256": g.sha256[:16],
                "opset": g.opset,
                "mib": round((manifest.root / g.file).stat().st_size / 2**20, 2),
            }
            for name, g in manifest.graphs[p].items()
        }
        for p in manifest.graphs
    }
    prov = manifest.provenance
    present = manifest.graph_names("fp32")
    tasks = {}
    for task, needed in MODEL_TASK_GRAPHS.items():
        missing = missing_graphs(task, present)
        tasks[task] = {"available": not missing, "graphs": list(needed), "missing": list(missing)}
    return {
        "dir": str(manifest.root),
        "arch": manifest.arch,
        "size": [manifest.height, manifest.width],
        "seq_length": manifest.seq_length,
        "random_init": manifest.random_init,
        "precisions": list(manifest.graphs),
        "graphs": graphs,
        "tasks": tasks,
        "provenance": {
            "checkpoint_stage": prov.checkpoint_stage,
            "checkpoint_step": prov.checkpoint_step,
            "training_command": prov.training_command,
            "data_dir": prov.data_dir,
            "git_commit": prov.git_commit,
            "export_date": prov.export_date,
        },
        "metrics": manifest.metrics,
        "model_card": card_summary(manifest.model_card),
        "int8_accuracy_delta": manifest.quantization.accuracy_delta if manifest.quantization else None,
    }


NOT_MEASURED = "not measured"


def card_summary(card: ModelCard | None) -> dict:
    """What the model was trained on and its measured scores (from the model card), or "not measured"."""
    if card is None:
        return {"trained_on": "not recorded", "real": NOT_MEASURED, "synthetic": NOT_MEASURED, "measured_in": None}
    scores = {
        key: [{**asdict(s), "verdict": s.verdict} for s in getattr(card, key)] or NOT_MEASURED
        for key in ("real", "synthetic")
    }
    return {
        "trained_on": card.trained_on,
        "synthetic_only": card.synthetic_only,
        **scores,
        "measured_in": card.measured_in,
    }


# ----------------------------------------------------------------------------- provenance
SOURCE_ROOT = Path(__file__).resolve().parents[2]  # the checkout holding this package, when run from one


def git_commit(root: Path | None = None, short: bool = False) -> str | None:
    """``git rev-parse [--short] HEAD`` in ``root`` (default: the checkout holding this package),
    or None where there is no git or no checkout (an installed wheel). Provenance of manifests,
    bench reports, the model card and the results report."""
    root = SOURCE_ROOT if root is None else Path(root)
    if not (root / ".git").exists():
        return None
    cmd = ["git", "-C", str(root), "rev-parse", *(["--short"] if short else []), "HEAD"]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None
