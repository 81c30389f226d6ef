"""The command line: every command has --help, errors are one line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from scmr_mesh.cli import build_parser, main


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sorted(sub.choices)


def test_top_level_help(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "scmr" in out and "demo" in out


@pytest.mark.parametrize("command", _commands())
def test_every_command_has_help(command, capsys):
    assert main([command, "--help"]) == 0
    assert capsys.readouterr().out.strip()


def test_unknown_command_is_usage_error(capsys):
    assert main(["no-such-command"]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_no_command_prints_help(capsys):
    assert main([]) == 2


def test_python_dash_m_entry_point():
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "scmr-mesh" in r.stdout


def test_command_home_names_the_module_of_every_command():
    import argparse
    import importlib

    from scmr_mesh.cli import COMMAND_HOME, COMMAND_MODULES

    found = {}
    for name in COMMAND_MODULES:
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(name).register(sub)
        found.update({cmd: name for cmd in sub.choices})
    assert COMMAND_HOME == found


def test_a_peer_command_loads_only_its_own_module():
    # `scmr cloud` is a peer's start-up path: no other area's command module
    code = ("import sys\nfrom scmr_mesh import cli\ncli.build_parser(['-v', 'cloud', '--node', 'x'], full=False)\n"
            "print(sorted(m for m in sys.modules if m.startswith('scmr_mesh') and m.endswith('commands')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "['scmr_mesh.mesh.commands']"


@pytest.mark.parametrize("argv", [["cloud", "--insecure", "--help"], ["bench", "mesh", "--help"], ["-v", "up", "--help"]])
def test_help_through_the_short_parser(argv, capsys):
    assert main(argv) == 0
    assert "usage: scmr " + next(a for a in argv if not a.startswith("-")) in capsys.readouterr().out


def test_a_sigterm_during_a_bench_runs_its_cleanup(monkeypatch):
    """`bench r2r` SIGTERMed left its peers running (reparented to init): the bench dispatcher turns
    SIGTERM into KeyboardInterrupt so the target's `finally` stops what it started."""
    import argparse
    import signal
    import sys
    import types

    from scmr_mesh.bench.commands import _handler

    cleaned = []

    def target(args):
        try:
            signal.raise_signal(signal.SIGTERM)  # its Python handler runs before this call returns
            pytest.fail("SIGTERM did not interrupt the bench")
        finally:
            cleaned.append(True)

    mod = types.ModuleType("scmr_mesh.bench._fake_target")
    mod.go = target
    monkeypatch.setitem(sys.modules, "scmr_mesh.bench._fake_target", mod)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        _handler("_fake_target", "go")(argparse.Namespace())
    assert cleaned
    assert signal.getsignal(signal.SIGTERM) is before  # restored
