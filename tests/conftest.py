"""Shared test helpers: where the real data lives, and how absent data is handled."""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    """Real data: $CGAMAP_DATA, else ../shared/data beside the repository."""
    env = os.environ.get("CGAMAP_DATA")
    if env:
        return Path(env)
    for cand in (REPO.parent / "shared" / "data", Path("/work/shared/data")):
        if cand.is_dir():
            return cand
    return REPO.parent / "shared" / "data"


def head_of_log(src: Path, dst: Path, scans: int) -> Path:
    """The start of a CARMEN log (gzip or not) up to its ``scans``-th FLASER line, written to
    ``dst`` (gzipped when its name ends in .gz)."""
    def opener(p: Path):
        return gzip.open if str(p).endswith(".gz") else open

    kept = 0
    with opener(src)(src, "rt") as fin, opener(dst)(dst, "wt") as fout:
        for line in fin:
            fout.write(line)
            kept += line.startswith("FLASER")
            if kept >= scans:
                break
    return dst


def require_data(relpath: str) -> Path:
    """Path of a real data file; skip when absent, but fail under CI (CI=true)."""
    path = data_dir() / relpath
    if not path.exists():
        msg = f"real data {relpath} not found under {data_dir()} (set CGAMAP_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session", autouse=True)
def _mapper_kernels():
    """The mapper's compiled kernels, built (or loaded from numba's cache) once before any
    test: uncached that takes ~10 s, which must not land inside one test's timeout.  A
    daemon a test starts then loads them from the cache, as the service does."""
    from cgamap.mapping.jit import warm_up

    warm_up()


@pytest.fixture
def shared_data():
    return require_data


@pytest.fixture
def cli_main(monkeypatch):
    """cgamap's real main() with only the device commands (``sim-device``, ``odom``,
    ``pantilt``): other areas' command modules may be mid-edit."""
    from cgamap.daemon import cli

    monkeypatch.setattr(cli, "COMMAND_MODULES", ["cgamap.daemon.cmd_sim",
                                                 "cgamap.daemon.cmd_base"])
    return cli.main
