"""The import arrows of DESIGN.md: cga <- mapping <- daemon; drivers use cga only."""

from __future__ import annotations

import ast

import pytest
from conftest import REPO

ALLOWED = {
    "cga": {"cga"},
    "drivers": {"cga", "drivers"},
    "mapping": {"cga", "mapping"},
    "calib": {"cga", "drivers", "mapping", "calib"},
    "daemon": {"cga", "drivers", "mapping", "calib", "daemon"},
}


def project_imports(path, layer: str) -> set[str]:
    """Top-level project layers a module imports (absolute cgamap.X or relative)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    rel_parts = path.relative_to(REPO).with_suffix("").parts
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = rel_parts[: len(rel_parts) - node.level]
                target = list(base) + (node.module.split(".") if node.module else [])
                if target:
                    found.add(target[0])
                continue
            names = [node.module or ""]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "cgamap" and len(parts) > 1:
                found.add(parts[1])
    return found


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_imports_point_down(layer):
    bad = []
    for path in sorted((REPO / layer).rglob("*.py")):
        extra = project_imports(path, layer) - ALLOWED[layer]
        if extra:
            bad.append(f"{path.relative_to(REPO)} imports {sorted(extra)}")
    assert not bad, "layer arrows broken:\n" + "\n".join(bad)
