"""rerun flags: parsing, fan-out to peers, and nothing rerun-related without them."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh import keys, viz
from scmr_mesh.errors import InputError


def fleet_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scmr up")
    viz.add_rerun_args(p)
    return p


def peer_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scmr robot")
    p.add_argument("--connect", action="append", default=[])  # Zenoh's flag must not clash
    viz.add_rerun_peer_args(p)
    return p


def test_no_flag_means_no_options():
    assert viz.RerunOptions.from_args(fleet_parser().parse_args([])) is None
    assert viz.RerunOptions.from_args(peer_parser().parse_args(["--connect", "tcp/127.0.0.1:7447"])) is None
    assert viz.fleet_viz(None, robots=["r0"]) is None
    assert viz.robot_viz(None, "r0") is None


@pytest.mark.parametrize(
    ("argv", "mode", "target"),
    [
        (["--save", "run.rrd"], "save", "run.rrd"),
        (["--spawn"], "spawn", None),
        (["--serve"], "serve", None),
        (["--connect"], "connect", viz.DEFAULT_CONNECT_URL),
        (["--connect", "9000"], "connect", "rerun+http://127.0.0.1:9000/proxy"),
        (["--connect", "rerun+http://10.0.0.2:9877/proxy"], "connect", "rerun+http://10.0.0.2:9877/proxy"),
    ],
)
def test_each_flag(argv, mode, target):
    opts = viz.RerunOptions.from_args(fleet_parser().parse_args(argv))
    assert (opts.mode, opts.target, opts.recording_id) == (mode, target, None)


def test_recording_id_passes_through():
    opts = viz.RerunOptions.from_args(fleet_parser().parse_args(["--spawn", "--rerun-recording-id", "abc"]))
    assert opts.recording_id == "abc"


@pytest.mark.parametrize("argv", [["--save", "a.rrd", "--spawn"], ["--serve", "--connect"], ["--spawn", "--serve"]])
def test_flags_are_mutually_exclusive(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        fleet_parser().parse_args(argv)
    assert exc.value.code == 2
    assert "not allowed with" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["http://127.0.0.1:9876", "rerun+http://127.0.0.1:9876/", "localhost", "0", "70000"])
def test_bad_connect_url_names_value(bad):
    with pytest.raises(InputError, match=re.escape(repr(bad) if not bad.isdigit() else bad)):
        viz.RerunOptions.from_args(fleet_parser().parse_args(["--connect", bad]))


def test_save_needs_rrd_suffix():
    with pytest.raises(InputError, match="run.txt"):
        viz.RerunOptions.from_args(fleet_parser().parse_args(["--save", "run.txt"]))


@given(port=st.integers(1, 65535), rid=st.text("abcdef0123456789", min_size=1, max_size=32))
@settings(max_examples=50, deadline=None)
def test_child_args_round_trip_into_peer_parser(port, rid):
    """What the fleet hands a child parses back into the same sink and recording."""
    url = viz.normalize_url(port)
    args = ["--rerun-url", url, "--rerun-recording-id", rid]
    opts = viz.RerunOptions.from_args(peer_parser().parse_args(["--connect", "tcp/127.0.0.1:1", *args]))
    assert opts == viz.RerunOptions("connect", url, rid)


def test_peer_save_flag():
    opts = viz.RerunOptions.from_args(peer_parser().parse_args(["--rerun-save", "r0.rrd"]))
    assert opts == viz.RerunOptions("save", "r0.rrd", None)


def test_connect_to_nothing_fails_fast_with_clear_error():
    from conftest import free_port

    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    with pytest.raises(viz.ViewerError, match="no rerun viewer listens"):
        viz.check_reachable(url)


def test_cli_without_flags_never_imports_rerun(repo_root, tmp_path):
    """Building the whole CLI and parsing fleet commands imports no rerun."""
    code = (
        "import sys\n"
        "from scmr_mesh import cli, viz\n"
        "p = cli.build_parser()\n"
        "import argparse; q = argparse.ArgumentParser(); viz.add_rerun_args(q)\n"
        "assert viz.RerunOptions.from_args(q.parse_args([])) is None\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'rerun_bindings')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]"
    assert list(tmp_path.iterdir()) == []  # and nothing was written


# -- masks -> class ids --------------------------------------------------------


def test_mask_classes_bool_uint8_and_red_green():
    m = np.array([[True, False], [False, True]])
    expect = np.array([[1, 2], [2, 1]], np.uint8)
    assert np.array_equal(viz._mask_to_classes(m), expect)
    assert np.array_equal(viz._mask_to_classes(m.astype(np.uint8) * 255), expect)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[m] = (0, 255, 0)
    rgb[~m] = (255, 0, 0)
    assert np.array_equal(viz._mask_to_classes(rgb), expect)


def test_mask_bad_shape_names_shape():
    with pytest.raises(InputError, match=r"\(2, 2, 2, 2\)"):
        viz._mask_to_classes(np.zeros((2, 2, 2, 2)))


@given(st.lists(st.booleans(), min_size=1, max_size=400))
@settings(max_examples=50, deadline=None)
def test_mask_classes_partition(bits):
    m = np.array(bits).reshape(1, -1)
    c = viz._mask_to_classes(m)
    assert set(np.unique(c)) <= {1, 2}
    assert int((c == 1).sum()) == int(m.sum())


# -- environment fallback for runners that pass no flags (scmr scenario run) ---


def test_for_peer_prefers_flags_then_env(monkeypatch, tmp_path):
    for k in (viz.ENV_URL, viz.ENV_SAVE_DIR, viz.ENV_RECORDING_ID):
        monkeypatch.delenv(k, raising=False)
    bare = peer_parser().parse_args([])
    assert viz.RerunOptions.for_peer(bare, "r1") is None
    monkeypatch.setenv(viz.ENV_RECORDING_ID, "rid")
    monkeypatch.setenv(viz.ENV_SAVE_DIR, str(tmp_path))
    opts = viz.RerunOptions.for_peer(bare, "r1")
    assert opts.mode == "save" and opts.recording_id == "rid"
    assert Path(opts.target).parent == tmp_path and Path(opts.target).name.startswith("r1-")
    monkeypatch.setenv(viz.ENV_URL, "9001")
    assert viz.RerunOptions.for_peer(bare, "r1") == viz.RerunOptions("connect", "rerun+http://127.0.0.1:9001/proxy", "rid")
    flagged = peer_parser().parse_args(["--rerun-save", "x.rrd"])
    assert viz.RerunOptions.for_peer(flagged, "r1") == viz.RerunOptions("save", "x.rrd", None)


def test_peers_env_session_without_options_changes_nothing(monkeypatch):
    monkeypatch.delenv(viz.ENV_URL, raising=False)
    with viz.peers_env_session(None, robots=["r0"]) as fv:
        assert fv is None
        assert viz.ENV_URL not in os.environ


@pytest.mark.parametrize(("raw", "name"), [("cloud0", "cloud0"), ("cloud | leader,r1", "cloud_leader_r1"), ("//", "_")])
def test_entity_name(raw, name):
    assert viz.entity_name(raw) == name
    keys.check_name(viz.entity_name(raw))


def test_every_serving_tier_has_its_own_level_above_failed():
    """A frame served by the peer tier was drawn at -1, as a failure, in the tier plot."""
    from scmr_mesh.qos.metrics import TIERS
    from scmr_mesh.viz.common import TIER_LEVEL

    levels = [TIER_LEVEL[t] for t in TIERS]
    assert min(levels) > TIER_LEVEL["failed"] and len(set(levels)) == len(TIERS)
    assert levels == sorted(levels, reverse=True)  # drawn in the order robots try them
