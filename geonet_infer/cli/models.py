"""``geonet-infer models``: the models a name reaches (bundled and converted); ``models rm NAME``."""

from __future__ import annotations

import argparse
import json

from geonet_infer.cli import COMMANDS


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "models",
        help=COMMANDS["models"],
        description="List the models --model NAME and geonet_infer.load(NAME) find: the bundled ones and those "
        "`geonet-infer convert` wrote to your models folder ($GEONET_INFER_HOME/models, else the cache folder). "
        "`geonet-infer models rm NAME` deletes a converted one (only inside that folder).",
    )
    parser.add_argument("action", nargs="?", choices=("list", "rm"), default="list")
    parser.add_argument("name", nargs="?", help="the converted model to remove (rm)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(run=run)


def describe(name: str, path, origin: str) -> dict:
    """One row: what the manifest says of the model, or why it cannot be read."""
    from geonet_infer.errors import GeoNetError
    from geonet_infer.models.manifest import load_manifest

    row: dict = {"name": name, "origin": origin, "path": str(path)}
    try:
        m = load_manifest(path, verify_files=False)
    except GeoNetError as err:
        return {**row, "error": err.problem}
    files = {e.file for graphs in m.graphs.values() for e in graphs.values()}
    sources = m.provenance.sources or []
    return {
        **row,
        "arch": m.arch,
        "size": [m.height, m.width],
        "seq_length": m.seq_length,
        "graphs": sorted({g for graphs in m.graphs.values() for g in graphs}),
        "precisions": list(m.precisions),
        "megabytes": round(sum((path / f).stat().st_size for f in files if (path / f).is_file()) / 1e6, 1),
        "from": [f"{s['checkpoint']} (sha256 {next(iter(s['sha256'].values()), '?')[:12]})" for s in sources]
        or ["random weights" if m.random_init else f"our training (stage {m.provenance.checkpoint_stage or '?'})"],
    }


def run(args: argparse.Namespace) -> int:
    from geonet_infer.errors import InputError
    from geonet_infer.models import bundled_models, remove_model, user_models, user_models_dir

    if args.action == "rm":
        if not args.name:
            raise InputError(None, "models rm needs a NAME", "`geonet-infer models` lists them")
        print(f"removed {remove_model(args.name)}")
        return 0
    rows = [describe(n, p, "bundled") for n, p in bundled_models().items()]
    rows += [describe(n, p, "converted") for n, p in user_models().items()]
    if args.json:
        print(json.dumps({"models_folder": str(user_models_dir()), "models": rows}, indent=2))
        return 0
    print(f"models folder: {user_models_dir()}")
    for r in rows:
        if "error" in r:
            print(f"{r['name']:<24} {r['origin']:<9} unreadable: {r['error']}")
            continue
        print(
            f"{r['name']:<24} {r['origin']:<9} {r['arch']:<8} {r['size'][0]}x{r['size'][1]} seq {r['seq_length']}  "
            f"{','.join(r['graphs'])}  {','.join(r['precisions'])}  {r['megabytes']:.1f} MB  "
            f"from {'; '.join(r['from'])}"
        )
    return 0
