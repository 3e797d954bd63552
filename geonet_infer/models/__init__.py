"""Models by name: the bundled ones (package data) and those ``geonet-infer convert`` wrote for this user.

Each sub-folder holding a ``manifest.json`` is a model, named after the folder. The bundled ones
are reproduced by ``scripts/build_bundled_model.sh`` from our own training code (``docs/models.md``
is their model card). Converted ones live in the user's models folder, :func:`user_models_dir`:
``$GEONET_INFER_HOME/models`` when that variable is set, else ``geonet-infer/models`` in the
platform's cache folder (``$XDG_CACHE_HOME`` or ``~/.cache`` on Linux, ``~/Library/Caches`` on
macOS, ``%LOCALAPPDATA%`` on Windows), as rembg and fastembed keep theirs.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from pathlib import Path

from geonet_infer.conventions import MANIFEST_NAME
from geonet_infer.errors import InputError, ModelError

MODELS_DIR = Path(__file__).resolve().parent
DEFAULT_MODEL = "small_synth"
HOME_VARIABLE = "GEONET_INFER_HOME"
NAME_RULE = "letters, digits, '_', '-' and '.', starting with a letter or digit, at most 64"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
CONVERTED_MARK = "geonet-infer convert"  # in the manifest's provenance of every converted model
_WORK_SUFFIX = re.compile(r"\.(tmp|old)-")  # a conversion's temporary folders beside its model


def bundled_models() -> dict[str, Path]:
    """Name -> directory of every bundled model."""
    return {p.name: p for p in sorted(MODELS_DIR.iterdir()) if (p / MANIFEST_NAME).is_file()}


def user_models_dir() -> Path:
    """The folder of this user's converted models (see the module docstring); not created here."""
    home = os.environ.get(HOME_VARIABLE)
    if home:
        return Path(home).expanduser() / "models"
    if sys.platform == "win32":
        cache = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        cache = Path.home() / "Library" / "Caches"
    else:
        cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "geonet-infer" / "models"


def is_model_name(text: str) -> bool:
    """Whether ``text`` has the form of a model name (not a path: no separator, no ``..``)."""
    return bool(_NAME.fullmatch(text)) and ".." not in text and not _WORK_SUFFIX.search(text)


def check_name(name: str) -> str:
    """``name`` if it can name a converted model; InputError saying why not."""
    if not is_model_name(name):
        raise InputError(None, f"model name {name!r}: not a name", f"use {NAME_RULE}; no '/', no '..'")
    if name in bundled_models():
        raise InputError(None, f"model name {name!r} is the bundled model's", "choose another name")
    return name


def user_models() -> dict[str, Path]:
    """Name -> directory of every converted model of this user (none when the folder is missing)."""
    folder = user_models_dir()
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return {}
    return {
        p.name: p for p in entries if is_model_name(p.name) and not p.is_symlink() and (p / MANIFEST_NAME).is_file()
    }


def resolve_model(model: str | Path | None = None) -> Path:
    """None -> the default bundled model; a bundled or converted name -> its directory; else a model
    directory path (``./NAME`` reaches a folder in the current directory that shares a model's name)."""
    bundled = bundled_models()
    name = DEFAULT_MODEL if model is None else str(model)
    if name in bundled:
        return bundled[name]
    if isinstance(model, str) and is_model_name(name):
        converted = user_models_dir() / name
        if (converted / MANIFEST_NAME).is_file() and not converted.is_symlink():
            return converted
    path = Path(model) if model is not None else MODELS_DIR / DEFAULT_MODEL
    if path.is_dir():
        return path
    names = ", ".join([*bundled, *user_models()]) or "none installed"
    raise ModelError(
        path,
        "no such model directory or model name",
        f"pass a model name ({names}; `geonet-infer models` lists them), a directory written by "
        "`geonet-infer convert --out` or `python -m export`, or convert one: "
        "`geonet-infer convert CHECKPOINT --name NAME`",
    )


def remove_model(name: str) -> Path:
    """Delete the converted model ``name`` from the user's models folder (nothing outside it); its path."""
    check_name(name)
    folder = user_models_dir()
    path = folder / name
    if path.is_symlink() or not (path / MANIFEST_NAME).is_file():
        raise InputError(path, "no converted model of this name here", "`geonet-infer models` lists them")
    if path.resolve().parent != folder.resolve():  # a name is one folder inside it, never a way out
        raise InputError(path, "is not inside the models folder", "remove it by hand")
    if CONVERTED_MARK not in (path / MANIFEST_NAME).read_text(errors="replace"):
        raise InputError(path, "was not written by geonet-infer convert: left as it is", "remove it by hand")
    shutil.rmtree(path)
    return path
