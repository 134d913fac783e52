"""Run every benchmark module (bench/bench_*.py, each with ``run() -> dict``) and write JSON.

Usage: python -m bench.run [--out bench/results.json] [--only NAME ...]
Figures are measured on this machine in this run; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

# Single-threaded BLAS unless the caller says otherwise (set before any module imports
# numpy): on a shared 2-core machine threaded BLAS spins against other processes and makes
# small matrix products erratic and up to 10x slower.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default=str(HERE / "results.json"))
    ap.add_argument("--only", nargs="*", help="module names without the bench_ prefix")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE.parent / "tests"))  # conftest.data_dir: one data setting
    names = sorted(p.stem for p in HERE.glob("bench_*.py"))
    if args.only:
        names = [n for n in names if n.removeprefix("bench_") in args.only]
    results: dict = {
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or
                    platform.machine(), "when": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                              time.gmtime())},
    }
    failed = 0
    for name in names:
        t0 = time.perf_counter()
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        try:
            module = importlib.import_module(f"bench.{name}")
            results[name.removeprefix("bench_")] = module.run()
        except Exception as exc:  # one broken benchmark must not hide the others
            failed += 1
            traceback.print_exc()
            results[name.removeprefix("bench_")] = {"error": f"{type(exc).__name__}: {exc}"}
        print(f"[bench] {name} done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    Path(args.out).write_text(json.dumps(results, indent=2, default=float) + "\n")
    print(json.dumps(results, indent=2, default=float))
    print(f"[bench] wrote {args.out}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
