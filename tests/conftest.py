"""Shared fixtures.

``realdata``: the shared real-data folder ``../shared/realdata`` (next to the repository).
Tests that use it are skipped when it is missing, except on CI (env var ``CI`` set to
anything but ``""``, ``0``, ``false`` or ``no``), where a missing folder is a failure:
there the data is expected, and a silent skip would hide that nothing was tested.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REALDATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"


def on_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_realdata(rel: str = "") -> Path:
    """``../shared/realdata/<rel>``; if it is missing: fail on CI, skip otherwise."""
    path = REALDATA / rel
    if not path.exists():
        msg = f"{path} not present (real test data, see ../shared/realdata/README.md)"
        if on_ci():
            pytest.fail(f"{msg}; CI is set, so missing real data is an error", pytrace=False)
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session")
def realdata() -> Path:
    """Path of ``../shared/realdata`` (fails on CI / skips elsewhere when it is missing)."""
    return require_realdata()
