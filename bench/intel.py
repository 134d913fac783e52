"""The Intel log and the maps built from it, shared by the benchmarks: one read of the log
and one build per odometry-noise seed in a ``make bench`` run."""

from __future__ import annotations

from functools import lru_cache

LOG = "laser/intel-corrected.log.gz"


def missing() -> dict | None:
    """The benchmark's result when the log is absent (None when it is there)."""
    from conftest import data_dir  # bench/run.py puts tests/ on sys.path

    if (data_dir() / LOG).exists():
        return None
    return {"skipped": f"{LOG} not found under {data_dir()}"}


@lru_cache(maxsize=1)
def scans() -> tuple:
    from cgamap.drivers.carmen import read_scans
    from conftest import data_dir

    return tuple(read_scans(data_dir() / LOG))


@lru_cache(maxsize=4)
def build(seed: int = 0):
    """``map build`` with ``--odom-noise high --seed seed``, default parameters."""
    from cgamap.mapping.offline import build_map, log_odometry

    s = list(scans())
    return build_map(s, log_odometry(s, "high", seed)[0])
