"""Every numeric and path flag of every command refuses unusable values (issue #12, item 6).

Table-driven, the way ``tests/test_cli.py`` walks ``--help``: the test walks
every command's arguments, requires each numeric flag to use a
:class:`scmr_mesh.cliargs.Number` (or a wrapped project parser) and each path
flag a :class:`scmr_mesh.cliargs.PathArg`, and feeds each one NaN,
infinities, out-of-range and unusable values: the answer is one line naming
the flag, the value and the fix, and exit status 1.  The commands themselves
never run (their handlers are replaced by a stub that fails the test).
"""

from __future__ import annotations

import argparse
import re
import os
import subprocess
import sys
from pathlib import Path

import pytest

from scmr_mesh import cli
from scmr_mesh.cliargs import Number, PathArg

#: Metavars (and positional names) that mean "a number" or "a path".
NUMERIC_METAVARS = {"N", "S", "HZ", "MS", "R", "Q", "P", "L", "BYTES", "SIZE", "SEED", "PORT", "DAYS", "X"}
PATH_METAVARS = {"DIR", "FILE", "PATH", "TOML", "PNG", "OUT.png", "FILE.rrd", "FILE|URL", "IMAGE", "FILE.json",
                 "folder", "file", "files", "dir", "images"}
#: Flags that take text that is parsed into numbers with units ("23Mb/s", "5e9", "1MB").
UNIT_FLAGS = {"--bandwidth-up", "--bandwidth-down", "--leader-bandwidth-up", "--leader-bandwidth-down",
              "--cycles", "--cpu-seconds", "--up", "--down", "--leader-hz", "--rtt", "--deadline",
              "--cloud-factor", "--reply-bytes", "--down-up-ratio", "--sizes", "--bandwidths", "--kill-cloud",
              "--cloud-outage", "--crash-outage", "--since", "--until", "--size"}


_BUILD = cli.build_parser


def _stubbed_parser() -> argparse.ArgumentParser:
    parser = _BUILD()

    def ran(args):  # a value that passed parsing: the command would have run
        return 99

    def stub(p: argparse.ArgumentParser) -> None:
        if p.get_default("func") is not None:
            p.set_defaults(func=ran)
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sp in a.choices.values():
                    stub(sp)

    stub(parser)
    return parser


def _walk(p: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in sorted(a.choices.items()):
                yield from _walk(sp, (*path, name))
        elif not isinstance(a, (argparse._HelpAction, argparse._VersionAction, argparse._CountAction,
                                argparse._StoreConstAction, argparse.BooleanOptionalAction)) and a.nargs != 0:
            yield path, a


ACTIONS = list(_walk(cli.build_parser()))


def _name(a: argparse.Action) -> str:
    return a.option_strings[-1] if a.option_strings else a.dest


def _is_numeric(a) -> bool:
    return (a.type in (int, float) or isinstance(a.type, Number) or (a.metavar in NUMERIC_METAVARS)
            or _name(a) in UNIT_FLAGS)


def _is_path(a) -> bool:
    return a.type is Path or isinstance(a.type, PathArg) or a.metavar in PATH_METAVARS or (
        not a.option_strings and a.dest in PATH_METAVARS)


def _id(item) -> str:
    path, a = item
    return " ".join((*path, _name(a)))


#: Path arguments checked by their command instead, with the reason.
EXEMPT = {
    "segment images": "a batch: each unusable image gets its own error line and the others are still "
                      "processed (tests/test_imaging_cli.py)",
}
NUMERIC = [x for x in ACTIONS if _is_numeric(x[1])]
PATHS = [x for x in ACTIONS if _is_path(x[1]) and not _is_numeric(x[1]) and _id(x) not in EXEMPT]


def test_the_walk_finds_the_flags_of_every_command():
    names = {_id(x) for x in ACTIONS}
    assert {"robot --rate", "robot --priority", "up --run-dir", "cloud --max-request-bytes",
            "robot --ready-file", "bench mesh --rate", "ods range --since"} <= names
    assert len(NUMERIC) > 60 and len(PATHS) > 50


@pytest.mark.parametrize("item", NUMERIC, ids=_id)
def test_every_numeric_flag_uses_a_checked_type(item):
    path, a = item
    assert isinstance(a.type, Number) or getattr(a.type, "kind", None) == "parsed", (
        f"scmr {_id(item)} takes a number but its type is {a.type!r}: use scmr_mesh.cliargs "
        "(Number/positive/count/non_negative, or parsed() for values with units)")


@pytest.mark.parametrize("item", PATHS, ids=_id)
def test_every_path_flag_uses_a_checked_type(item):
    path, a = item
    assert isinstance(a.type, PathArg), (
        f"scmr {_id(item)} takes a path but its type is {a.type!r}: use scmr_mesh.cliargs.PathArg")


def _argv(path, a, value: str) -> list[str]:
    return [*path, a.option_strings[-1], value] if a.option_strings else [*path, value]


def _check_refused(monkeypatch, capsys, path, a, value: str) -> None:
    monkeypatch.setattr(cli, "build_parser", lambda *args, **kw: _stubbed_parser())
    rc = cli.main(_argv(path, a, value))
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    flag = a.option_strings[-1] if a.option_strings else None
    assert rc == 1, f"scmr {' '.join(_argv(path, a, value))} -> exit {rc} (99: accepted), stderr {err!r}"
    assert len(lines) == 1 and lines[0].startswith("scmr: error: "), err
    if flag:
        assert flag in lines[0], err
    assert ("e.g." in lines[0] or "give" in lines[0]) and "Traceback" not in err, err


NUMERIC_CASES = [(p, a, v) for p, a in NUMERIC for v in (a.type.bad_values() if hasattr(a.type, "bad_values")
                                                         else ["nan", "inf", "-inf"])]


@pytest.mark.parametrize("path,a,value", NUMERIC_CASES, ids=[f"{_id((p, a))}={v}" for p, a, v in NUMERIC_CASES])
def test_a_numeric_flag_refuses_nan_infinities_and_out_of_range(monkeypatch, capsys, path, a, value):
    _check_refused(monkeypatch, capsys, path, a, value)


def _probe_parser():
    from scmr_mesh.bench.probe import build_parser

    return build_parser()


PROBE_CASES = [(p, a, v) for p, a in _walk(_probe_parser()) if _is_numeric(a) or isinstance(a.type, PathArg)
               for v in (a.type.bad_values() if hasattr(a.type, "bad_values") else ["/no/such/folder"])]


@pytest.mark.parametrize("path,a,value", PROBE_CASES,
                         ids=[f"bench zenoh {_id((p, a))}={v}" for p, a, v in PROBE_CASES])
def test_the_probe_options_of_bench_zenoh_refuse_bad_values(capsys, path, a, value):
    """``scmr bench zenoh PROBE --opt VALUE``: the probe's own parser, same rules."""
    assert isinstance(a.type, (Number, PathArg)), f"bench zenoh {_id((path, a))} has type {a.type!r}"
    with pytest.raises(SystemExit) as ei:
        _probe_parser().parse_args(_argv(path, a, value))
    lines = capsys.readouterr().err.strip().splitlines()
    assert ei.value.code == 1 and len(lines) == 1 and lines[0].startswith(f"scmr: error: {_name(a)} "), lines


@pytest.fixture(scope="module")
def unusable(tmp_path_factory):
    """Paths no flag can use: missing, under a file, and (root) on a read-only file system."""
    base = tmp_path_factory.mktemp("unusable")
    afile = base / "a-file"
    afile.write_text("x")
    out = {"missing": str(base / "no" / "such" / "thing"), "under-a-file": str(afile / "x"),
           "a-file": str(afile), "a-folder": str(base),
           # a folder that takes no new files even for root (issue 25: --ready-file /proc/nope/ready
           # started the workers, then ended in "internal error: FileNotFoundError")
           "no-new-files": "/proc/nope/x"}
    ro = base / "ro"
    ro.mkdir()
    mounted = False
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)]).returncode == 0
    if mounted:
        out["read-only"] = str(ro / "run")
    try:
        yield out
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(ro)])


def _bad_paths(mode: str) -> list[str]:
    return {"in-file": ["missing", "a-folder"], "in-dir": ["missing", "a-file"], "in-path": ["missing"],
            "out-file": ["under-a-file", "a-folder", "read-only", "no-new-files"],
            "out-dir": ["under-a-file", "a-file", "read-only", "no-new-files"]
            }[mode]


PATH_CASES = [(p, a, k) for p, a in PATHS if isinstance(a.type, PathArg) for k in _bad_paths(a.type.mode)]


@pytest.mark.parametrize("path,a,kind", PATH_CASES, ids=[f"{_id((p, a))}={k}" for p, a, k in PATH_CASES])
def test_a_path_flag_refuses_an_unusable_path(monkeypatch, capsys, unusable, path, a, kind):
    if kind not in unusable:
        pytest.skip("a read-only file system needs root (mount)")
    _check_refused(monkeypatch, capsys, path, a, unusable[kind])


# ---------------------------------------------------- the issue's reproductions (real processes)
def _scmr(*args: str, cwd=None, timeout: float = 60) -> subprocess.CompletedProcess:
    try:
        return subprocess.run([sys.executable, "-m", "scmr_mesh", *args], capture_output=True, text=True,
                              timeout=timeout, cwd=cwd)
    except subprocess.TimeoutExpired:
        pytest.fail(f"scmr {' '.join(args)} still ran after {timeout:g} s (the value was accepted)")


@pytest.mark.parametrize("args,flag", [
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--rate", "inf"], "--rate"),
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--rate", "nan"], "--rate"),
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--duration", "nan"], "--duration"),
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--priority", "-1"], "--priority"),
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--priority", "2000000"], "--priority"),
    (["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", "{tmp}/r", "--deadline-ms", "nan"], "--deadline-ms"),
    (["cloud", "--insecure", "--node", "c1", "--max-request-bytes", "-1"], "--max-request-bytes"),
    (["up", "--robots", "1", "--duration", "1", "--synthetic", "stub", "--rate", "inf"], "--rate"),
    (["up", "--robots", "1", "--synthetic", "stub", "--duration", "nan"], "--duration"),
])
def test_the_issues_bad_values_are_refused_before_anything_starts(tmp_path, args, flag):
    r = _scmr(*[x.replace("{tmp}", str(tmp_path)) for x in args], cwd=tmp_path, timeout=30)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1, r.stderr
    assert len(lines) == 1 and lines[0].startswith(f"scmr: error: {flag} "), r.stderr
    assert not (tmp_path / "r").exists()  # refused before the robot made its folders


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="mounting needs root")
def test_up_refuses_a_run_dir_on_a_read_only_file_system(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)], check=True)
    try:
        r = _scmr("up", "--robots", "1", "--run-dir", str(ro / "run"), cwd=tmp_path)
    finally:
        subprocess.run(["umount", "-l", str(ro)])
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip() == (f"scmr: error: --run-dir {ro / 'run'}: {ro} is on a read-only file system; "
                                "give a folder that can be created or written, e.g. --run-dir runs/my-run")


def test_a_ready_file_in_a_missing_folder_is_created(tmp_path):
    """A missing folder with a writable ancestor is usable: the peer creates it."""
    ready = tmp_path / "not" / "yet" / "r1.ready"
    r = _scmr("robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--process", "scmr_mesh.mesh.testing:stub_process",
              "--out", str(tmp_path / "r1"), "--count", "1", "--wait-ms", "0", "--connect", "tcp/127.0.0.1:1",
              "--ready-file", str(ready), "--log-file", str(tmp_path / "logs" / "r1.log"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr + (tmp_path / "logs" / "r1.log").read_text()
    assert (tmp_path / "logs" / "r1.log").stat().st_size > 0
    r = _scmr("robot", "--id", "r1", "--synthetic", "stub", "--out", str(tmp_path / "r1"),
              "--ready-file", str(tmp_path / "r1" / "records.jsonl" / "r1.ready"), cwd=tmp_path)
    assert r.returncode == 1 and r.stderr.startswith("scmr: error: --ready-file ") and "is a file" in r.stderr


#: A zero the help promises a meaning for ("0 skips it", "0 = the real pipeline", "default 0: ...").
ZERO_HELP = re.compile(r"(?<![\d.,])0 ?(skips|=|:)")
ZERO_FLAGS = [x for x in NUMERIC if ZERO_HELP.search(x[1].help or "")]


def test_the_zero_walk_finds_the_documented_zeros():
    assert {"bench mesh --overload-robots", "bench mesh --crash-robots", "bench tls --fleet-runs"} <= {
        _id(x) for x in ZERO_FLAGS}


@pytest.mark.parametrize("item", ZERO_FLAGS, ids=_id)
def test_a_flag_whose_help_gives_zero_a_meaning_accepts_zero(item):
    """`--overload-robots 0` was refused although its help said "0 skips it"."""
    path, a = item
    try:
        a.type("0")
    except Exception as exc:  # the flag's own type refuses what its help offers
        pytest.fail(f"scmr {_id(item)} 0 is refused ({exc}) but its help says {a.help!r}")
