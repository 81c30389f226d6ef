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
