"""Released TF checkpoints -> a model directory, with no torch and no TensorFlow.

    from geonet_infer.convert.build import ConvertConfig, convert
    convert(ConvertConfig(checkpoints=("~/geonet_depthnet/model",), out=Path("models/official_depth")))

The graphs come from the templates shipped in the package (:mod:`.templates`, 128x416), or from a
folder of templates made for another size by ``python -m export --from-tf`` (which calls this
function: one conversion). The directory is written as ``OUT.tmp-XXXX`` beside OUT and renamed
when complete, so OUT is either absent or whole, also when two conversions race for one name.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from geonet_infer.convert import manifest as cmf
from geonet_infer.convert.official import GRAPH_OF_KIND, SCOPES, Selection, official_conventions, select_networks
from geonet_infer.convert.onnx_writer import write_graph
from geonet_infer.convert.templates import TEMPLATES_DIR, Template, initializers, template_name
from geonet_infer.errors import InputError
from geonet_infer.models.manifest import PRECISIONS, GraphEntry, Provenance, load_manifest, write_manifest

GRAPH_NAMES = ("depthnet", "posenet", "rigidflow", "resflownet")
KIND_OF_GRAPH = {g: k for k, g in GRAPH_OF_KIND.items()}
CONVERTED_STAGE = "official TensorFlow release (geonet-infer convert)"


@dataclass
class ConvertConfig:
    """What to convert. ``checkpoints``: ``PREFIX`` or ``KIND=PREFIX`` items (:func:`.official.parse_spec`)."""

    checkpoints: tuple[str, ...]
    out: Path
    precisions: tuple[str, ...] = ("fp32",)
    calib_data: Path | None = None  # folder of consecutive frames for INT8 calibration
    quant: object | None = None  # geonet_infer.convert.quantize.QuantSettings (default settings when None)
    scale_normalize: bool = False  # the model_sn release: each disparity map over its mean, in the graph
    graphs: tuple[str, ...] = GRAPH_NAMES  # narrowed to what the checkpoints hold
    templates: Path = TEMPLATES_DIR
    force: bool = False  # replace an existing OUT
    log: Callable[[str], None] = field(default=lambda msg: print(msg, file=sys.stderr, flush=True))
    before_publish: Callable[[Path], None] | None = None  # e.g. --verify on the finished directory


# ------------------------------------------------------------------------------ directory
def make_tmp_dir(out: Path) -> Path:
    """An empty ``OUT.tmp-XXXX`` beside ``out`` (0755: a model directory is meant to be shared)."""
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f"{out.name}.tmp-", dir=parent))
    except OSError as exc:
        raise InputError(
            parent, f"cannot create the output directory here ({exc.strerror or exc})", "choose a writable location"
        ) from None
    os.chmod(tmp, 0o755)
    return tmp


def publish(tmp: Path, out: Path, force: bool) -> None:
    """Rename the finished ``tmp`` onto ``out``, so a reader sees the old or the new directory, never a mix.

    Without ``force`` an ``out`` that exists (or appeared meanwhile: another conversion to the same name
    won) is refused. With ``force`` the existing ``out`` is moved aside and removed; when two forced
    conversions race, each retries until its rename lands (the last one wins, nothing is left over).
    """
    aside: list[Path] = []
    try:
        for _ in range(PUBLISH_TRIES):
            try:
                os.rename(tmp, out)  # atomic; fails while a (non-empty) out exists
                return
            except OSError as exc:
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) and not out.exists():
                    raise
                if not force:
                    raise InputError(
                        out, "already exists (another conversion wrote it meanwhile)", "pass --force or choose another"
                    ) from None
            old = Path(tempfile.mkdtemp(prefix=f"{out.name}.old-", dir=out.parent))
            os.rmdir(old)
            try:
                os.replace(out, old)
                aside.append(old)
            except FileNotFoundError:  # another forced conversion moved it first: try again
                continue
        raise InputError(
            out, f"could not be published after {PUBLISH_TRIES} tries", "other conversions keep replacing it"
        )
    finally:
        for old in aside:
            shutil.rmtree(old, ignore_errors=True)


PUBLISH_TRIES = 20


# ------------------------------------------------------------------------------ conversion
def _graphs(cfg: ConvertConfig, sel: Selection) -> list[str]:
    available = {GRAPH_OF_KIND[k] for k in sel.specs} | {"rigidflow"}
    if tuple(cfg.graphs) == GRAPH_NAMES:  # the default: everything the checkpoints give
        graphs = [g for g in GRAPH_NAMES if g in available]
    else:
        lacking = [g for g in cfg.graphs if g not in available]
        if lacking:
            raise InputError(
                None,
                f"--graphs {','.join(lacking)}: the checkpoints hold no network for it",
                f"they give {', '.join(g for g in GRAPH_NAMES if g in available)}",
            )
        graphs = [g for g in GRAPH_NAMES if g in cfg.graphs]
    if "resflownet" in graphs and not {"depthnet", "posenet"} <= set(graphs):
        raise InputError(
            None,
            "resflownet.onnx needs depthnet and posenet too (its input is their rigid flow)",
            "the released flow checkpoint holds all three: convert it whole",
        )
    if cfg.scale_normalize and "depth" not in sel.specs:
        raise InputError(None, "--scale-normalize applies to a depth_net, and none is converted")
    return graphs


def _templates(cfg: ConvertConfig, graphs: list[str], arch: str, seq_length: int) -> dict:
    out = {}
    for graph in graphs:
        name = template_name(graph, arch=arch, seq_length=seq_length, sn=cfg.scale_normalize)
        if not (Path(cfg.templates) / f"{name}.json").is_file():
            raise InputError(
                None,
                f"no conversion template {name} for this model",
                "the package ships templates of the released networks at 128x416; "
                "other sizes: python -m export --from-tf --height H --width W (repository, torch)",
            )
        out[graph] = Template.load(name, Path(cfg.templates))
    sizes = {(t.recipe["height"], t.recipe["width"]) for t in out.values()}
    if len(sizes) != 1:
        raise InputError(cfg.templates, f"templates of several sizes {sorted(sizes)}", "make them at one size")
    return out


def _precisions(cfg: ConvertConfig) -> list[str]:
    bad = [p for p in cfg.precisions if p not in PRECISIONS]
    if bad or "fp32" not in cfg.precisions:
        raise InputError(
            None, f"--precision {','.join(cfg.precisions)}", "use fp32 or fp32,int8 (int8 is calibrated with fp32)"
        )
    if "int8" in cfg.precisions and cfg.calib_data is None:
        raise InputError(
            None, "--precision int8 needs --calib-data DIR", "a folder of consecutive frames like those you will run on"
        )
    if "int8" not in cfg.precisions and cfg.calib_data is not None:
        raise InputError(None, "--calib-data only applies to --precision fp32,int8")
    return [p for p in PRECISIONS if p in cfg.precisions]


def check_output(out: Path, force: bool) -> None:
    if out.exists() and not force:
        raise InputError(out, "already exists", "pass --force to replace it, or choose another name")
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a directory", "choose another output")


def convert(cfg: ConvertConfig) -> Path:
    """Write the model directory ``cfg.out``; returns its path. GeoNetError on bad input (nothing written)."""
    out = Path(cfg.out)
    precisions = _precisions(cfg)
    check_output(out, cfg.force)
    if "int8" in precisions:
        from geonet_infer.convert.int8 import import_quantize
        from geonet_infer.io import list_images

        import_quantize()  # the missing extra, before minutes of converting
        list_images(cfg.calib_data)
    started = time.perf_counter()
    sel = select_networks(cfg.checkpoints, cfg.log)
    graphs = _graphs(cfg, sel)
    arch, seq_length = sel.arch, sel.seq_length()
    templates = _templates(cfg, graphs, arch, seq_length)
    first = next(iter(templates.values())).recipe
    height, width = first["height"], first["width"]
    alpha = templates["rigidflow"].recipe["photometric_alpha"] if "rigidflow" in templates else 0.85
    tmp = make_tmp_dir(out)
    try:
        cfg.log(f"converting {arch} {height}x{width} seq {seq_length} -> {out}")
        fp32: dict[str, GraphEntry] = {}
        for graph, template in templates.items():
            t0 = time.perf_counter()
            meta = cmf.graph_metadata(graph, arch, height, width, seq_length, "fp32", False, alpha)
            kind = KIND_OF_GRAPH.get(graph)
            tensors = initializers(template, sel.checkpoints[kind], SCOPES[kind]) if kind else iter(())
            write_graph(tmp / f"{graph}.onnx", template.head.read_bytes(), meta, tensors)
            exporter = f"{template.recipe['exporter']}; weights from the TF checkpoint by geonet-infer convert"
            fp32[graph] = cmf.graph_entry(
                tmp, f"{graph}.onnx", template.recipe["io"], template.recipe["opset"], "fp32", exporter
            )
            size = (tmp / f"{graph}.onnx").stat().st_size / 2**20
            cfg.log(f"  fp32 {graph}.onnx  {size:.1f} MiB  ({time.perf_counter() - t0:.1f} s)")
        for ckpt in sel.checkpoints.values():
            ckpt.reader.close()
        all_graphs: dict = {"fp32": fp32}
        quant = None

        def manifest_over(graph_sets: dict, quantization=None):
            return cmf.build_manifest(
                height=height,
                width=width,
                seq_length=seq_length,
                arch=arch,
                random_init=False,
                graphs=graph_sets,
                prov=_provenance(arch, sel, templates),
                metrics={},
                quantization=quantization,
                photometric_alpha=alpha,
            )

        if "int8" in precisions:
            from geonet_infer.convert.int8 import import_quantize, quantize_directory

            settings = cfg.quant or import_quantize().QuantSettings()
            int8, quant = quantize_directory(
                tmp,
                fp32,
                arch=arch,
                height=height,
                width=width,
                seq_length=seq_length,
                calib_data=Path(cfg.calib_data),  # type: ignore[arg-type]
                settings=settings,
                write_interim=lambda graph_sets: _write(manifest_over(graph_sets), tmp),
                log=cfg.log,
            )
            all_graphs["int8"] = int8
            quant = dataclasses.replace(
                quant,
                accuracy_delta_reason="not measured: converted from TensorFlow checkpoints (score both precisions "
                "with geonet-infer eval --precision fp32|int8)",
            )
        manifest = manifest_over(all_graphs, quant)
        official = official_conventions(sel.specs, cfg.scale_normalize)
        if sel.notes:
            official["notes"] = sel.notes
        manifest = dataclasses.replace(manifest, conventions={**manifest.conventions, "official_tf": official})
        write_manifest(manifest, tmp)
        load_manifest(tmp)  # the directory must validate before it is published
        if cfg.before_publish is not None:
            cfg.before_publish(tmp)
        publish(tmp, out, cfg.force)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    cfg.log(f"done: {out} ({time.perf_counter() - started:.1f} s)")
    return out


def _write(manifest, folder: Path) -> None:
    write_manifest(manifest, folder)


def _provenance(arch: str, sel: Selection, templates: dict) -> Provenance:
    exporters = sorted({t.recipe["exporter"] for t in templates.values()})
    made_with = next(iter(templates.values())).recipe.get("made_with", {})
    return Provenance(
        architecture=arch,
        random_init=False,
        export_date=cmf.utc_now(),
        checkpoint=" + ".join(s["path"] for s in sel.sources),
        checkpoint_stage=CONVERTED_STAGE,
        checkpoint_step=sel.sources[0]["global_step"] if len(sel.sources) == 1 else None,
        exporter="; ".join(exporters) + " (architecture templates); weights by geonet-infer convert",
        versions={**cmf.versions(), **{f"templates: {k}": v for k, v in made_with.items()}},
        sources=sel.sources,
    )
