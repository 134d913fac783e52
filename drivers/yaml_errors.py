"""One line for a YAML file that does not parse, the same wherever the stack reads YAML.

It lives in ``drivers`` because that is the lowest layer reading YAML (stereo calibration
files); ``calib`` and ``daemon`` import it from here (``mapping`` reads only JSON).
"""

from __future__ import annotations

import yaml


def yaml_error_text(exc: yaml.YAMLError, what: str = "YAML syntax error") -> str:
    """``"<what> at line L, column C: <problem>"`` for a ``MarkedYAMLError`` (1-based, from
    its problem mark); other YAML errors give the first line of their own message.  Never
    more than one line: callers prefix the file name or the option."""
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    problem = (getattr(exc, "problem", None) or str(exc)).strip()
    return f"{what}{where}: {problem.splitlines()[0] if problem else type(exc).__name__}"
