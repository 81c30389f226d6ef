"""The import rules of the layout (README "Layout"): dependencies point inward.

Layers, lowest first; a module may import its own layer and the ones below:

=========  ==================================================================
base       ``errors``, ``_lazy``, ``_schema``, ``wire``, ``keys``, ``cliargs`` (shared argparse types),
           ``vocab`` (the control vocabulary: tiers and other enums), ``_cpu`` (the usable cores),
           ``ports`` (free loopback ports outside the ephemeral range), ``deathsig`` (the kernel's parent-death
           signal for the children the project starts)
core       ``imaging/``, ``energy/``, ``data/``, ``qos/``, ``security/``, ``ros/``, and the
           pure scenario modules ``scenario/spec.py``, ``scenario/plan.py``, ``scenario/radio.py``
mesh       ``mesh/``: every Zenoh import of the running system
viz        ``viz/``: every rerun import
procs      ``fleet/``, ``scenario/`` (processes and faults), ``thesis/`` (``scmr thesis``: runs scenarios,
           reports on them); may use mesh and viz
commands   every ``*/commands.py`` (CLI wiring): anything but the bench layer
bench      ``bench/``: every ``scmr bench`` target; imports whatever it measures
cli        ``cli.py``, ``__main__.py``: the only importers of ``bench``
=========  ==================================================================

Imports inside functions count too (a lazy import is still a dependency).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "scmr_mesh"

RANK = {"base": 0, "core": 1, "mesh": 2, "viz": 2, "procs": 3, "commands": 4, "bench": 5, "cli": 6}
CORE = ("imaging", "energy", "data", "qos", "security", "ros")


def layer(rel: Path) -> str:
    """The layer of a module path relative to the package."""
    parts = rel.parts
    if rel.name == "commands.py":
        return "commands"
    if len(parts) == 1:
        stem = rel.stem
        if stem in ("cli", "__main__"):
            return "cli"
        if stem in ("errors", "_lazy", "_schema", "wire", "keys", "cliargs", "vocab", "_cpu", "ports", "deathsig",
                    "__init__"):
            return "base"
        raise AssertionError(f"top-level module {rel} has no layer; add it to tests/test_layers.py")
    top = parts[0]
    if top in CORE:
        return "core"
    if top == "scenario" and rel.name in ("spec.py", "plan.py", "radio.py", "__init__.py"):
        return "core"
    if top in ("mesh", "viz", "bench"):
        return top
    if top in ("fleet", "scenario", "thesis"):
        return "procs"
    raise AssertionError(f"package {top}/ has no layer; add it to tests/test_layers.py")


def module_path(name: str) -> Path | None:
    """``scmr_mesh.a.b`` -> path relative to the package (module or package ``__init__``)."""
    parts = name.split(".")[1:]
    if not parts:
        return Path("__init__.py")
    base = PKG.joinpath(*parts)
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py").relative_to(PKG)
    if (base / "__init__.py").is_file():
        return (base / "__init__.py").relative_to(PKG)
    return None


def imports(path: Path) -> list[tuple[str, int]]:
    """Absolute module names imported anywhere in ``path``, with line numbers."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.module, node.lineno))
            if node.module == "scmr_mesh" or node.module.startswith("scmr_mesh."):
                # `from scmr_mesh.fleet import procs` imports the submodule procs
                for a in node.names:
                    sub = f"{node.module}.{a.name}"
                    if module_path(sub) is not None:
                        out.append((sub, node.lineno))
    return out


FILES = sorted(p for p in PKG.rglob("*.py"))


def test_every_module_has_a_layer():
    for f in FILES:
        layer(f.relative_to(PKG))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PKG)))
def test_dependencies_point_inward(path):
    rel = path.relative_to(PKG)
    mine = layer(rel)
    bad = []
    for name, line in imports(path):
        if not name.startswith("scmr_mesh"):
            continue
        target = module_path(name)
        if target is None:
            continue
        theirs = layer(target)
        if theirs == "bench" and mine not in ("bench", "cli"):
            bad.append(f"line {line}: {name} (only the CLI imports the bench layer)")
        elif RANK[theirs] > RANK[mine] or (RANK[theirs] == RANK[mine] and theirs != mine):
            bad.append(f"line {line}: {name} ({mine} may not import {theirs})")
    assert not bad, f"{rel} ({mine}) imports upward: " + "; ".join(bad)


def _importers(module: str) -> list[str]:
    return [str(p.relative_to(PKG)) for p in FILES
            if any(n.split(".")[0] == module for n, _ in imports(p))]


def test_zenoh_only_in_mesh_and_bench():
    offenders = [f for f in _importers("zenoh") if Path(f).parts[0] not in ("mesh", "bench")]
    assert offenders == []


def test_rerun_only_in_viz():
    offenders = [f for f in _importers("rerun") if Path(f).parts[0] != "viz"]
    assert offenders == []


def test_pure_core_has_no_middleware():
    for f in FILES:
        rel = f.relative_to(PKG)
        if layer(rel) in ("base", "core"):
            bad = {n.split(".")[0] for n, _ in imports(f)} & {"zenoh", "rerun"}
            assert not bad, f"{rel} imports {bad}"


#: Core modules that are command-line entry points of their own (``python -m ...``).
CORE_ENTRY_POINTS = {"imaging/_aot.py"}


def core_violations(rel: Path, path: Path) -> set[str]:
    """Imports of process management or flag parsing in the core module ``path`` (at ``rel``)."""
    if layer(rel) != "core" or rel.as_posix() in CORE_ENTRY_POINTS:
        return set()
    bad = {n.split(".")[0] for n, _ in imports(path)} & {"subprocess", "argparse"}
    bad |= {n for n, _ in imports(path) if n == "scmr_mesh.cliargs" or n.startswith("scmr_mesh.fleet")}
    return bad


def test_core_folders_start_no_process_and_parse_no_flags():
    """Folders are layers (issue 21): starting servers (``data/pgserver.py`` -> ``fleet/``) and flag parsing
    (the negotiator's flags -> ``mesh/negotiation.py``) left the pure core; ``*/commands.py`` is the CLI layer."""
    for f in FILES:
        rel = f.relative_to(PKG)
        bad = core_violations(rel, f)
        assert not bad, f"{rel} imports {bad}: process management belongs in fleet/, flags in */commands.py"


def test_the_rules_catch_a_process_or_flags_in_the_core(tmp_path):
    """The checker itself: subprocess in data/, argparse or cliargs in qos/ are reported; commands.py may parse."""
    bad = tmp_path / "x.py"
    bad.write_text("import subprocess\nfrom argparse import Namespace\nfrom scmr_mesh import cliargs as ca\n")
    assert core_violations(Path("data/pgserver.py"), bad) == {"subprocess", "argparse", "scmr_mesh.cliargs"}
    assert core_violations(Path("qos/negotiator.py"), bad) == {"subprocess", "argparse", "scmr_mesh.cliargs"}
    assert core_violations(Path("qos/commands.py"), bad) == set()
    assert core_violations(Path("fleet/pgserver.py"), bad) == set()


def test_the_rules_catch_an_upward_import(tmp_path):
    """The checker itself: a core module importing the mesh is reported."""
    bad = tmp_path / "x.py"
    bad.write_text("from scmr_mesh.mesh.robot import Robot\n")
    names = [n for n, _ in imports(bad)]
    assert "scmr_mesh.mesh.robot" in names
    assert RANK[layer(module_path("scmr_mesh.mesh.robot"))] > RANK[layer(Path("data/queue.py"))]
