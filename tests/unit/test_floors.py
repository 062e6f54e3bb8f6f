"""The tree's floors (DESIGN.md "Target layout"): an import only points down.

core ``quadlink`` imports nothing of the project; the algorithms (``perception``) only the core; each process
(``sim_sitl``, ``firmware_bridge``, ``companion``, ``teleop``) the algorithms and the core, never another
process (the bridge takes no perception code either); the tools (``harness``) anything. Imports inside
functions count: a lazy import that runs back up is still a cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("quadlink", "perception", "sim_sitl", "firmware_bridge", "companion", "teleop", "harness")
ALLOWED: dict[str, set[str]] = {
    "quadlink": set(),
    "perception": {"quadlink"},
    "sim_sitl": {"quadlink", "perception"},
    "firmware_bridge": {"quadlink"},
    "companion": {"quadlink", "perception"},
    "teleop": {"quadlink", "perception"},
    "harness": set(PACKAGES),
}


def project_imports(package: str) -> dict[str, set[str]]:
    """{imported top-level project package: files of ``package`` that import it} (relative imports stay inside)."""
    found: dict[str, set[str]] = {}
    for path in (REPO / package).rglob("*.py"):
        if "generated" in path.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in PACKAGES and top != package:
                    found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_only_point_down(package: str) -> None:
    wrong = {top: sorted(files) for top, files in project_imports(package).items() if top not in ALLOWED[package]}
    assert not wrong, f"{package} imports a floor above or beside it: {wrong}"


def test_the_checker_sees_an_upward_import(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The walk finds a function-level import (the kind that hid the old cycle)."""
    pkg = tmp_path / "quadlink"
    pkg.mkdir()
    (pkg / "x.py").write_text("def f():\n    from sim_sitl.runner import Sitl\n    return Sitl\n")
    monkeypatch.setattr(__import__(__name__), "REPO", tmp_path)
    assert project_imports("quadlink") == {"sim_sitl": {"quadlink/x.py"}}
