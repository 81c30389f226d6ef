"""Dependencies point inward: the pure core imports neither Zenoh nor rerun,
Zenoh is imported only under scmr_mesh/mesh/, rerun only in scmr_mesh/viz.py."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "scmr_mesh"


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def _files():
    return sorted(p for p in PKG.rglob("*.py"))


def test_zenoh_only_in_mesh_package():
    offenders = [
        str(p.relative_to(PKG)) for p in _files()
        if "zenoh" in _imports(p) and "mesh" not in p.relative_to(PKG).parts[:1]
    ]
    assert offenders == []


def test_rerun_only_in_viz_module():
    offenders = [str(p.relative_to(PKG)) for p in _files() if "rerun" in _imports(p) and p.name != "viz.py"]
    assert offenders == []


def test_pure_core_has_no_middleware():
    core = [PKG / "imaging", PKG / "energy", PKG / "wire.py", PKG / "scenario" / "spec.py"]
    for root in core:
        files = [root] if root.suffix == ".py" else list(root.rglob("*.py"))
        for f in files:
            if f.exists():
                bad = _imports(f) & {"zenoh", "rerun"}
                assert not bad, f"{f.relative_to(PKG)} imports {bad}"
