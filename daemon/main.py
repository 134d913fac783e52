"""``cgamapd``: the mapping daemon's entry point.

    cgamapd [--config FILE] [--replay FILE] [--state-dir DIR] [--socket PATH]
    cgamapd --check-config FILE

Exit codes follow sysexits.h where systemd cares: 78 (EX_CONFIG) for a bad configuration,
0 after a clean SIGTERM/SIGINT shutdown with a final checkpoint.
"""

from __future__ import annotations

import argparse
import logging
import sys

from cgamap.daemon import config as config_mod

DEFAULT_CONFIG = "/etc/cgamap/robot.yaml"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cgamapd", description="cgamap mapping daemon")
    p.add_argument("--config", "-c", default=None,
                   help=f"YAML config (default: $CONFIGURATION_DIRECTORY/robot.yaml or "
                        f"{DEFAULT_CONFIG})")
    p.add_argument("--check-config", metavar="FILE", help="validate FILE and exit (78 if bad)")
    p.add_argument("--replay", metavar="FILE",
                   help="take input from an MCAP recording or a CARMEN log, not devices")
    p.add_argument("--replay-rate", type=float, default=0.0,
                   help="replay speed factor (0: as fast as the mapper goes)")
    p.add_argument("--exit-after-replay", action="store_true",
                   help="checkpoint and exit when the replay is exhausted")
    p.add_argument("--state-dir", help="override paths.state_dir")
    p.add_argument("--socket", help="override the query socket path")
    p.add_argument("--log-level", choices=config_mod.LOG_LEVELS, help="override log_level")
    return p


def default_config_path() -> str:
    import os

    d = os.environ.get("CONFIGURATION_DIRECTORY", "").split(":")[0]
    return f"{d}/robot.yaml" if d else DEFAULT_CONFIG


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    path = args.check_config or args.config or default_config_path()
    try:
        cfg = config_mod.load(path)
    except config_mod.ConfigError as exc:
        print(f"cgamapd: {path}: {exc}", file=sys.stderr)
        return config_mod.EX_CONFIG
    if args.check_config:
        print(f"cgamapd: {path}: ok ({len(cfg['devices'])} devices)")
        return 0
    level = (args.log_level or cfg["log_level"]).upper()
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")  # journald adds the time
    from cgamap.daemon.service import Daemon

    daemon = Daemon(cfg, config_path=path, replay=args.replay, replay_rate=args.replay_rate,
                    state_dir=args.state_dir, socket_path=args.socket,
                    exit_after_replay=args.exit_after_replay)
    return daemon.run()


if __name__ == "__main__":
    sys.exit(main())
