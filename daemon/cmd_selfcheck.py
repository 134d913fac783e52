"""``cgamap selfcheck``: prove the installed algebra's identities (a pass/fail table)."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("selfcheck", help="check the CGA identities on this installation")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cgamap.cga import selfcheck

    results = selfcheck.run(args.seed)
    ok = all(passed for _, passed, _ in results)
    if args.json:
        print(json.dumps({"passed": ok, "checks": [
            {"name": n, "passed": p, "max_error": e} for n, p, e in results]}))
    else:
        width = max(len(n) for n, _, _ in results)
        print(f"{'identity':<{width}}  result  max error")
        for name, passed, err in results:
            print(f"{name:<{width}}  {'pass' if passed else 'FAIL':<6}  {err:.2e}")
        print(f"{sum(p for _, p, _ in results)}/{len(results)} identities pass")
    return 0 if ok else 1
