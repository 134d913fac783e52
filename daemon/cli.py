"""The ``cgamap`` command line: one entry point, subcommands registered by modules.

Each feature module exposes ``register(subparsers)`` that adds its subcommands and sets
``func`` on them; the list below is the only place that names them.  A subcommand's
function returns the process exit code.  Bad input is reported as one line on stderr
(``cgamap: <what>: <problem>``) with a non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import select
import sys
from importlib.metadata import PackageNotFoundError, version

# Modules that add subcommands (imported lazily so `cgamap --version` stays fast).
COMMAND_MODULES = [
    "cgamap.daemon.cmd_selfcheck",
    "cgamap.daemon.cmd_lasers",
    "cgamap.daemon.cmd_sim",
    "cgamap.daemon.cmd_base",
    "cgamap.daemon.cmd_mapping",
    "cgamap.daemon.cmd_planes",
    "cgamap.daemon.cmd_stereo",
    "cgamap.daemon.cmd_daemon",
    "cgamap.calib.cli",
]


class UsageError(Exception):
    """Raised by a subcommand for bad input: printed as one line, exit code 2 (or .code).

    ``main`` reports any exception that carries an ``exit_code`` attribute the same way, so
    lower layers (``calib``) define their own error class instead of importing this one.
    """

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code

    @property
    def exit_code(self) -> int:
        return self.code


def package_version() -> str:
    try:
        return version("cgamap")
    except PackageNotFoundError:  # running from a source tree without install
        return "0+unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cgamap", description="Robot sensing and mapping in conformal geometric algebra."
    )
    parser.add_argument("--version", action="version", version=f"cgamap {package_version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # feature not present in this build
                continue
            raise
        module.register(sub)
    return parser


def _stdout_closed() -> bool:
    """Whether stdout is a pipe whose reader went away (as opposed to, say, a socket)."""
    try:
        sys.stdout.flush()
    except (BrokenPipeError, ValueError):
        return True
    except OSError:
        return False
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not raise again
    (the recipe of the Python docs, "Note on SIGPIPE")."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (AttributeError, OSError, ValueError):
        pass


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError as exc:
        if _stdout_closed():   # `cgamap ... | head`: the reader has all it wanted
            _silence_stdout()
            return 0
        print(f"cgamap: the other end closed the connection ({exc})", file=sys.stderr)
        return 74
    except Exception as exc:
        code = getattr(exc, "exit_code", None)
        if code is None:
            raise
        print(f"cgamap: {exc}", file=sys.stderr)
        return int(code)


if __name__ == "__main__":
    sys.exit(main())
