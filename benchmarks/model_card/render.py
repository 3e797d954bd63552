"""The model card's Markdown, one function per section, and the card's summary in the manifest."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

from benchmarks import eval_all
from benchmarks.markdown import sig3, signed3
from benchmarks.markdown import table as _table
from benchmarks.model_card.measure import (
    BASELINE_LABEL,
    KITTI_CROP,
    MIN_DEPTH,
    PRECISION_LABEL,
    _flatten,
    _mib,
)
from benchmarks.model_card.tables import (
    HEADLINES,
    _before_after,
    _camera_height_limitation,
    _camera_height_text,
    _checkpoint_text,
    _compare,
    _data_kitti,
    _data_synth,
    _depth_table,
    _floor_text,
    _flow_table,
    _headline,
    _pose_table,
    _stage_origin,
)
from experiments import real_pose_experiment
from geonet_infer.eval.datasets import SNIPPET
from geonet_infer.io.atomic import atomic_write
from geonet_infer.models.manifest import MANIFEST_NAME, load_manifest

# ----------------------------------------------------------------------------- manifest
METRIC_NAMES = {"abs_rel": "AbsRel", "noc.epe": "EPE-noc (px)", "ate_snippet.mean": "ATE (paper ÷N, mean)"}


def manifest_card(result: dict, card_path: str) -> dict:
    """The manifest's ``model_card`` block: what the model was trained on and the card's headline
    FP32 numbers, each beside its baseline (the same rows as the card's before/after table)."""
    m = result["model"]
    prov = m["provenance"]
    if m["random_init"]:
        trained_on, synthetic_only = "nothing: random-init weights (timing only)", False
    elif prov.get("sources"):
        trained_on, synthetic_only = f"the released GeoNet TensorFlow checkpoints ({prov['checkpoint']})", False
    elif result.get("real_training"):
        trained_on, synthetic_only = f"synthetic scenes made by training.synth, then {result['real_training']}", False
    else:
        data = f" ({prov['data_dir']})" if prov.get("data_dir") else ""
        trained_on, synthetic_only = f"synthetic scenes only{data}, made by training.synth", True
    data = {"kitti": _data_kitti(result).replace("`", ""), "synthetic": _data_synth(result).replace("`", "")}
    scores: dict[str, list] = {"real": [], "synthetic": []}
    for h in HEADLINES:
        scores["real" if h.where == "kitti" else "synthetic"].append(
            {
                "task": h.task,
                "metric": METRIC_NAMES[h.metric],
                "data": data[h.where],
                "value": _headline(result, h, "fp32"),
                "baseline": BASELINE_LABEL[h.baseline].removesuffix(" (baseline)"),
                "baseline_value": _flatten(result[h.where][h.task][h.baseline])[h.metric],
                "lower_is_better": True,
            }
        )
    return {
        "trained_on": trained_on,
        "synthetic_only": synthetic_only,
        "measured_in": card_path,
        "generated_utc": result["generated_utc"],
        **scores,
    }


def write_manifest_card(model_dir: str | Path, card: dict) -> Path:
    """Put ``card`` into the model directory's manifest as ``model_card``; every other key and the
    graph files stay as they are (the manifest is rewritten atomically, the graphs are not touched)."""
    path = Path(model_dir) / MANIFEST_NAME
    raw = json.loads(path.read_text())
    raw["model_card"] = card
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(raw, indent=2) + "\n")
    load_manifest(model_dir)  # what the runtime will read back: refuse to leave a manifest it cannot load
    return path


def render_card(result: dict) -> str:
    """The Markdown card of a result (:func:`run`'s, or an earlier run's ``--json``), one function per section."""
    sections = (
        _header_section,
        _model_section,
        _before_after,
        _real_section,
        _experiment_sections,
        _files_section,
        _measured_section,
        _depth_section,
        _flow_pose_section,
        _int8_section,
        _limitations_section,
    )
    return "\n".join(line for section in sections for line in section(result)) + "\n"


def _real_section(result: dict) -> list[str]:
    """Section "Real data": every real set with ground truth, from ``python -m benchmarks.eval_all`` (``--real``)."""
    real = result.get("real")
    if not real:
        return []
    body = eval_all.markdown(real).rstrip("\n").splitlines()
    return [
        "## Real data: every set in ../shared with ground truth",
        "",
        f"Measured by `{real['command']} --json {result.get('real_json', 'REAL.json')}` (from the repository "
        f"root; {real['generated_utc']}) and rendered here from that JSON by "
        f"`{result.get('real_render_command', 'python -m benchmarks.model_card --real REAL.json ...')}`; every "
        "number below comes from that run, scored by the code of `geonet-infer eval` (`benchmarks/eval_all.py` on "
        "`geonet_infer.eval`).",
        "",
        *body[2:],  # its first line (model, command, date) is said above
        "",
        *real_pose_experiment.trained_frames_note(result.get("experiments") or []),
    ]


# result key -> the experiment (experiments/<name>.py) whose render(rounds) draws its section
EXPERIMENTS = {
    "experiments": "real_pose_experiment",
    "teacher_rounds": "teacher_experiment",
    "stop_rounds": "stop_experiment",
}


def _experiment_sections(result: dict) -> list[str]:
    """The experiments' sections (issues 32, 46, 53), each drawn by its own module from its JSON rounds."""
    return [line for key, name in EXPERIMENTS.items() if result.get(key)
            for line in importlib.import_module(f"experiments.{name}").render(result[key])]  # fmt: skip


def _header_section(result: dict) -> list[str]:
    """Title, the command that regenerates the card, and the random-init warning."""
    m = result["model"]
    L = [
        f"# Model card: `{Path(m['dir']).name}`",
        "",
        "Regenerate this file (from the repository root; every number below comes from that run, "
        "none is typed by hand):",
        "",
        "```bash",
        result["command"],
        "```",
        "",
        f"Generated {result['generated_utc']} at git commit `{(result['git_commit'] or 'unknown')[:12]}` "
        "by `python -m benchmarks.model_card`. All models run through the pip runtime "
        "(`geonet_infer.core.predictor.Predictor` on onnxruntime), exactly as users run them.",
        "",
    ]
    if result.get("real"):
        L += [
            "The section *Real data* comes from `python -m benchmarks.eval_all` (its own command is given there) "
            f"and was added with `--real {result.get('real_json', 'REAL.json')}`.",
            "",
        ]
    if result.get("real_training"):
        L += [f'What the model was trained on says `--real-training "{result["real_training"]}"` too.', ""]
    if m["random_init"]:
        L += [
            "> **⚠️ WARNING: RANDOM-INIT MODEL. This card was generated with `--allow-random-init` for a "
            "model directory whose graphs hold random, untrained weights (`random_init: true` in the "
            "manifest). Its accuracy numbers measure noise and say nothing about GeoNet. Do not publish "
            "or compare them; regenerate the card from a trained export.**",
            "",
        ]
    return L


def _model_section(result: dict) -> list[str]:
    """Section "The model": architecture and provenance, then the manifest's training metrics and INT8 settings."""
    m = result["model"]
    prov = m["provenance"]
    origin = _stage_origin(prov.get("training_command"))
    stage = prov.get("checkpoint_stage")
    stages = (f"`{stage}`, {origin}" if origin else f"`{stage}`") if stage else "n/a"
    rows = [
        [
            "architecture",
            f"`{m['arch']}` (DepthNet, PoseNet"
            + (", ResFlowNet" if "resflownet" in m["graphs"] else "; no ResFlowNet: flow = rigid flow")
            + ")",
        ],
        ["graphs", ", ".join(f"`{g}`" for g in m["graphs"])],
        ["input size", f"{m['height']}×{m['width']}, snippets of {m['seq_length']} frames (target in the middle)"],
        ["precisions", ", ".join(m["precisions"])],
        ["random init", str(m["random_init"])],
        ["training data", f"`{prov['data_dir']}`" if prov.get("data_dir") else "n/a"],
        ["training stage", stages],
        [
            "training steps (this stage)",
            sig3(prov["checkpoint_step"]) if prov.get("checkpoint_step") is not None else "n/a",
        ],
        ["training command", f"`{prov['training_command']}`" if prov.get("training_command") else "n/a"],
        ["checkpoint", _checkpoint_text(prov)],
        ["exported", f"{prov.get('export_date')} at git commit `{(prov.get('git_commit') or 'unknown')[:12]}`"],
        ["exporter", prov.get("exporter") or "n/a"],
        ["versions", ", ".join(f"{k} {v}" for k, v in sorted(prov.get("versions", {}).items())) or "n/a"],
    ]
    L = ["## The model", "", *_table(["", ""], rows), ""]
    if m["metrics"]:
        L += [
            "Checkpoint metrics recorded by training (from the manifest; validation split of the "
            "training data, not the held-out sequences):",
            "",
        ]
        L += _table(
            ["metric", "value"],
            [[f"`{k}`", sig3(v) if isinstance(v, (int, float)) else str(v)] for k, v in _flatten(m["metrics"]).items()],
        ) + [""]
    q = m["quantization"]
    if q:
        L += [
            "INT8 quantisation (from the manifest): "
            f"{q.get('method')}, activations {q.get('activation_type')}, weights {q.get('weight_type')}, "
            f"per-channel {q.get('per_channel')}, reduce-range {q.get('reduce_range')}, calibration "
            f"`{q.get('calibrate_method')}` on `{q.get('calibration_data')}` "
            f"({', '.join(f'{g}: {n}' for g, n in (q.get('calibration_samples') or {}).items())} inputs); "
            f"graphs kept in FP32: {', '.join(q.get('fp32_graphs') or []) or 'none'}; operator types quantised: "
            f"{', '.join(q.get('op_types') or []) or 'every type onnxruntime quantises'}.",
            "",
        ]
        for graph, notes in (q.get("graph_notes") or {}).items():
            L += [f"- {graph}: {line}" for line in notes] + [""]
    return L


def _files_section(result: dict) -> list[str]:
    """Section "Files": every graph file with its size and sha256 prefix, and the totals."""
    m = result["model"]
    L = [
        "## Files",
        "",
        f"Model directory `{m['dir']}`; sha256 from `manifest.json` (checked against the "
        "files when the model was loaded).",
        "",
    ]
    L += _table(
        ["precision", "graph", "file", "size", "sha256 (prefix)"],
        [
            [
                f["precision"],
                f["graph"],
                f"`{f['file']}`" + (" (FP32)" if f["file_precision"] != f["precision"] else ""),
                _mib(f["bytes"]),
                f"`{f['sha256'][:12]}`",
            ]
            for f in m["files"]
        ],
    ) + [""]
    totals: dict[str, int] = {}
    for f in m["files"]:
        totals[f["precision"]] = totals.get(f["precision"], 0) + f["bytes"]
    L += [
        "Total per precision (a precision's set includes the shared FP32 `rigidflow`): "
        + ", ".join(f"{p} {_mib(b)}" for p, b in totals.items())
        + f"; the whole directory, manifest included: {m['dir_bytes']:,} bytes ({_mib(m['dir_bytes'])}).",
        "",
    ]
    return L


def _measured_section(result: dict) -> list[str]:
    """Section "What was measured": data, protocol and baselines of each task."""
    s, k = result["synthetic"], result["kitti"]
    orb = s["pose"]["orb_vo_baseline"]
    return [
        "## What was measured",
        "",
        f"* **Synthetic held-out**: {_data_synth(result)}: sequences {', '.join(f'`{x}`' for x in s['sequences'])} "
        f"listed in `{s['prepared_dir']}/heldout.txt`, generated by `training.synth` and never trained on"
        + (f"; one frame / pair / snippet in {s['stride']} (`--stride {s['stride']}`)" if s["stride"] > 1 else "")
        + ". Depth: every pixel with ground truth (no crop), per-image median scaling, clamp to "
        f"[{MIN_DEPTH:g}, {result['settings']['max_depth']:g}] m "
        "(`geonet_infer.eval.evaluation.evaluate_depth`). Flow t→t+1 from the snippet "
        + (
            "[t−1, t, t+1]"
            if result["settings"]["flow_seq_length"] == 3
            else "pair [t, t+1] (padded by the runtime; `evaluate_flow` passes triplets only)"
        )
        + ", EPE and Fl (EPE > 3 px and > 5 %) on non-occluded (noc) and all in-view (occ) pixels "
        "(`geonet_infer.eval.evaluation.evaluate_flow`).",
        f"* **Pose**: ATE on {SNIPPET}-frame snippets (every target t = 2 … N−3"
        + (f", stride {s['stride']}" if s["stride"] > 1 else "")
        + ") against the synthetic ground-truth "
        "poses (`poses.txt`, camera-to-world, inverted to world→camera and put in the snippet's first-frame "
        f"coordinates with `metrics.snippet_poses_to_global`). Model trajectory: {s['pose']['method']}. "
        "`ATE, paper` is `metrics.ate_snippet`, the SfMLearner/GeoNet value with its quirk kept: "
        "√(Σ‖e‖²)/N, i.e. the true RMSE ÷ √5, with only a scale (no rotation) fitted per snippet. "
        "`ATE, true RMSE` is `metrics.ate_rmse_true` after the same alignment "
        "(`geonet_infer.eval.evaluation.evaluate_pose`). Units are the synthetic world's metres.",
        f"* **Real KITTI**: {_data_kitti(result)}, never trained on. Ground truth: "
        + (
            "the Velodyne scans projected by `geonet_infer.eval.velodyne.velodyne_to_depth_map` (camera 2, Velodyne "
            "forward distance)"
            if k["ground_truth"] == "velodyne"
            else "the sparse depth PNGs of `proj_depth/groundtruth/image_02`"
        )
        + f". Eigen protocol: {KITTI_CROP.capitalize()} crop, {k['min_depth']:g} < GT < "
        f"{k['max_depth']:g} m, per-image median scaling (or the camera height, rows so labelled), then clamp; "
        "the runtime returns depth at the input resolution.",
        "* **Baselines**: *constant depth* predicts one value per image; after median scaling that is the "
        "image's median GT depth. *Zero flow* predicts no motion; *DIS medium* is OpenCV's DIS optical flow, "
        "medium preset, on grey frames (`geonet_infer.eval.baselines.dis_flow`). *Identity pose* predicts no camera "
        "motion; its ATE is the snippet's own extent. The per-snippet least-squares scale can shrink any "
        "prediction to zero, so a model's ATE can never exceed the identity baseline's on the same snippet: "
        "the baseline is an upper bound, and the gap to it is what the pose network contributes. *ORB-VO* is "
        "two-view ORB visual odometry per consecutive pair (5-point essential matrix, `recoverPose`, unit-length "
        "steps, then the same per-snippet scale; `geonet_infer.eval.baselines.orb_vo`); "
        f"{orb['failed_pairs']} of its {orb['pairs']} pairs failed and repeated the previous step. Every baseline "
        "is the function `geonet-infer eval --method` runs (`geonet_infer.eval.evaluation.baseline_fns`).",
        "",
    ]


def _per_frame_label(key: str) -> str:
    """Column header of the per-frame AbsRel table: "FP32", "FP32, camera height", "constant depth"."""
    if key.endswith("_camera_height"):
        return f"{PRECISION_LABEL[key[: -len('_camera_height')]].removeprefix('model, ')}, camera height"
    return PRECISION_LABEL.get(key, "constant depth")


def _per_frame_cell(row: dict) -> str:
    return "no ground plane" if row.get("ground_fit") == "failed" else sig3(row["abs_rel"])


def _depth_section(result: dict) -> list[str]:
    """Section "Depth": synthetic and KITTI tables, the depth-floor and camera-height notes, AbsRel per KITTI frame."""
    d, kd = result["synthetic"]["depth"], result["kitti"]["depth"]
    L = ["## Depth", "", "### Synthetic held-out sequences", ""]
    L += _depth_table(d, _data_synth(result), "frames") + [""]
    L += ["### Real KITTI (Velodyne ground truth)", ""]
    L += _depth_table(kd, _data_kitti(result), "frames") + [""]
    L += _floor_text(kd, result["before"]["kitti"]["depth"] if result["before"] else None)
    L += _camera_height_text(kd)
    L += ["Per KITTI frame (AbsRel):", ""]
    keys = [c for p in ("fp32", "int8") if p in kd for c in (p, f"{p}_camera_height")]
    keys.append("constant_baseline")
    L += _table(
        ["frame"] + [_per_frame_label(c) for c in keys] + ["GT pixels"],
        [
            [f["frame"]] + [_per_frame_cell(f[c]) for c in keys] + [sig3(f["constant_baseline"]["n_valid"])]
            for f in kd["per_frame"]
        ],
    ) + [""]
    return L


def _flow_pose_section(result: dict) -> list[str]:
    """Sections "Optical flow" and "Camera pose": their tables, and a warning per precision whose camera stays put."""
    s = result["synthetic"]
    synth_data = _data_synth(result)
    L = ["## Optical flow (synthetic held-out sequences)", ""]
    L += _flow_table(s["flow"], synth_data) + [""]
    L += ["## Camera pose (synthetic held-out sequences, 5-frame snippets)", ""]
    L += _pose_table(s["pose"], synth_data) + [""]
    for p in ("fp32", "int8"):
        n = s["pose"].get(p, {}).get("static_snippets", 0)
        if n:
            L += [
                f"**{PRECISION_LABEL[p]}: in {n} of {s['pose']['snippets']} snippets the predicted camera "
                "does not move at all** (every chained position exactly 0), so there its ATE is the identity "
                "baseline's. The pose matrices this precision returns carry no motion there; check its "
                "PoseNet graph.",
                "",
            ]
    return L


INT8_METRIC_NAMES = {
    "abs_rel": "AbsRel",
    "sq_rel": "SqRel",
    "rmse": "RMSE",
    "rmse_log": "RMSElog",
    "a1": "δ<1.25",
    "noc.epe": "EPE noc",
    "occ.epe": "EPE occ",
    "noc.fl": "Fl noc",
    "occ.fl": "Fl occ",
    "ate_snippet.mean": "ATE paper (mean)",
    "ate_rmse_true.mean": "ATE true RMSE (mean)",
}


def _int8_section(result: dict) -> list[str]:
    """Section "INT8 versus FP32": this run's differences, then the check the export recorded in the manifest."""
    m = result["model"]
    L = ["## INT8 versus FP32", ""]
    if result["int8_delta"]:
        data = {"synthetic": _data_synth(result), "kitti": _data_kitti(result)}
        L += [
            "Difference INT8 − FP32 on the same frames (positive = INT8 larger; for δ<1.25 larger is "
            "better, for the errors smaller is better):",
            "",
        ]
        L += _table(
            ["data", "task", "metric", "FP32", "INT8", "INT8 − FP32", "relative"],
            [
                [
                    data["synthetic"] if r["data"] == "synthetic" else data["kitti"],
                    r["task"],
                    INT8_METRIC_NAMES[r["metric"]],
                    sig3(r["fp32"]),
                    sig3(r["int8"]),
                    signed3(r["delta"]),
                    "n/a" if r["relative"] is None else signed3(100 * r["relative"]) + " %",
                ]
                for r in result["int8_delta"]
            ],
        ) + [""]
    else:
        L += [f"This model directory has no INT8 graphs (the manifest lists only {', '.join(m['precisions'])}).", ""]
    q = m["quantization"]
    if q and isinstance(q.get("accuracy_delta"), dict):
        acc = q["accuracy_delta"]
        rows = [
            [f"`{k}`", sig3(v["fp32"]), sig3(v["int8"]), signed3(v["delta"])]
            for k, v in acc.items()
            if isinstance(v, dict) and {"fp32", "int8", "delta"} <= set(v)
        ]
        if rows:
            L += [
                "For comparison, the INT8 check the export itself recorded in the manifest "
                "(`quantization.accuracy_delta`, also through the runtime's Predictor; "
                f"data `{acc.get('synth_dir')}`, stride {acc.get('stride')}):",
                "",
            ]
            L += _table(["metric", "FP32", "INT8", "INT8 − FP32"], rows) + [""]
    if q and q.get("accuracy_delta_reason"):
        L += [f"Export note on the INT8 check: {q['accuracy_delta_reason']}.", ""]
    return L


def _limitations_section(result: dict) -> list[str]:
    """Section "Limitations", with the FP32 numbers each one rests on."""
    m = result["model"]
    prov = m["provenance"]
    s, kd = result["synthetic"], result["kitti"]["depth"]
    best = "fp32"
    L = ["## Limitations", ""]
    if m["random_init"]:
        L += ["* **The weights are random (development card).** Nothing below describes a trained model."]
    trained_on = f" (`{prov['data_dir']}`)" if prov.get("data_dir") else ""
    if result.get("real_training"):
        data = (
            f"* **Mostly synthetic training data.** The model learned on procedurally generated driving sequences "
            "(`training.synth`: boxes on a flat road, Lambertian shading, no sensor noise; see "
            f"`docs/synthetic_data.md`), then {result['real_training']}; its last stage trained on{trained_on}."
        )
    else:
        data = (
            "* **Synthetic training data.** The model is trained only on procedurally generated driving "
            f"sequences{trained_on} (`training.synth`: boxes on a flat road, Lambertian shading, no sensor noise; "
            "see `docs/synthetic_data.md`)."
        )
    L += [
        data + " The held-out synthetic numbers come from the same generator and overstate what to expect on "
        "real video.",
        _real_depth_limitation(result),
        "* **Relative scale.** Depth and camera translation are known only up to an unknown scale. Every "
        "depth number except the camera-height rows uses per-image median scaling with the ground truth and "
        "every ATE a per-snippet scale fit, so those do not measure metric scale. " + _camera_height_limitation(kd),
        "* **Pose ATE on 5-frame snippets** hides drift and most rotation error, and the paper's value "
        "divides by N (it is the true RMSE ÷ √5). " + _real_pose_limitation(result),
        "* **Flow** is compared with zero flow and OpenCV DIS (medium preset), not with a learned flow method "
        f"(FP32 EPE noc {sig3(s['flow'][best]['noc']['epe'])} px vs "
        f"{sig3(s['flow']['zero_flow_baseline']['noc']['epe'])} px for zero flow and "
        f"{sig3(s['flow']['dis_medium_baseline']['noc']['epe'])} px for DIS medium" + _real_flow_limitation(result),
        "",
    ]
    return L


def _real_sets(result: dict, task: str) -> list[dict]:
    return [x for x in (result.get("real") or {}).get("sets", []) if x["task"] == task]


def _real_depth_limitation(result: dict) -> str:
    """The real-depth bullet: the test drive, and with ``--real`` the real validation frames."""
    kd, sd = result["kitti"]["depth"], result["synthetic"]["depth"]
    model, const = kd["fp32"]["abs_rel"], kd["constant_baseline"]["abs_rel"]
    synth_model, synth_const = sd["fp32"]["abs_rel"], sd["constant_baseline"]["abs_rel"]
    synth = (
        f"on the synthetic held-out set it is {sig3(synth_model)} vs {sig3(synth_const)} "
        f"({_compare(synth_model, synth_const)} the baseline)"
    )
    v = (result.get("real") or {}).get("validation") or {}
    if not v.get("metrics", {}).get("fp32"):
        return (
            f"* **Real-data depth is measured on {kd['frames']} KITTI frames only** (one drive, consecutive "
            f"frames, so they are far from independent). On them the FP32 model's AbsRel ({sig3(model)}) is "
            f"{_compare(model, const)} the constant-depth baseline ({sig3(const)}); {synth}. This is no "
            "substitute for the 697-image Eigen split."
        )
    vm, vc = v["metrics"]["fp32"]["abs_rel"], v["metrics"]["constant"]["abs_rel"]
    return (
        f"* **Real-data depth is measured on few frames.** On the test drive ({kd['frames']} consecutive frames "
        f"of one drive) the FP32 model's AbsRel ({sig3(model)}) is {_compare(model, const)} the constant-depth "
        f"baseline ({sig3(const)}); on the real validation frames ({v['frames']} frames of other drives and "
        f"scenes, see Real data) it is {sig3(vm)} vs {sig3(vc)} ({_compare(vm, vc)} the baseline); {synth}. "
        "This is no substitute for the 697-image Eigen split."
    )


def _real_pose_limitation(result: dict) -> str:
    sets = _real_sets(result, "pose")
    if not sets:
        return (
            "There is no real-data pose or flow evaluation here (the KITTI frames have no poses and no flow "
            "ground truth)."
        )
    per_set = "; ".join(
        f"{x['name']}: {sig3(x['results']['fp32']['metrics']['ate_snippet'])} vs ORB-VO "
        f"{sig3(x['results']['orb_vo']['metrics']['ate_snippet'])} and identity "
        f"{sig3(x['results']['identity']['metrics']['ate_snippet'])}"
        for x in sets
        if "fp32" in x["results"]
    )
    snippets = sum(x["items"] for x in sets)
    return f"On real KITTI odometry ({snippets} snippets, grey frames) the FP32 ATE (paper) is {per_set}."


def _real_flow_limitation(result: dict) -> str:
    """The end of the flow bullet: synthetic only, or also the real pairs of ``--real``."""
    sets = [x for x in _real_sets(result, "flow") if "fp32" in x["results"]]
    if not sets:
        return "), on synthetic data only."
    real = "; ".join(
        f"{x['name']} ({_count(x['items'], 'pairs')}): {sig3(x['results']['fp32']['metrics']['epe_noc'])} px vs "
        f"{sig3(x['results']['zero_flow']['metrics']['epe_noc'])} px and "
        f"{sig3(x['results']['dis_medium']['metrics']['epe_noc'])} px"
        for x in sets
    )
    return f" on synthetic data; on real KITTI flow, {real})."


def _count(n: int, label: str) -> str:
    return f"{n} {label if n != 1 else label.removesuffix('s')}"
