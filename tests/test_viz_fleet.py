"""``scmr up --save``: a real fleet (cloud, leader, 2 robots as processes on
loopback, stub processing) records one .rrd; every robot's frames in it match
the lines of its records.jsonl.  Also: ``scmr up`` without rerun flags starts
no rerun process and writes no .rrd.  ~25 s on a loaded 2-core machine.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from scmr_mesh import viz

STUB = ["--synthetic", "stub", "--server-arg=--process", "--server-arg=scmr_mesh.mesh.testing:stub_process",
        "--quiet", "--robots", "2", "--duration", "3", "--rate", "4"]


def scmr(*args: str) -> list[str]:
    return [sys.executable, "-m", "scmr_mesh", *args]


def rerun_processes(home: str) -> set[int]:
    """rerun viewer processes started with this test's ``HOME`` (a suite running beside this
    one on the same host starts its own: counting those failed two suites run at once)."""
    out = set()
    want = b"HOME=" + home.encode()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                exe = (d / "cmdline").read_bytes().split(b"\0")[0]
                if exe.endswith(b"rerun_cli/rerun") and want in (d / "environ").read_bytes().split(b"\0"):
                    out.add(int(d.name))
            except OSError:
                continue
    return out


@pytest.fixture()
def env(tmp_path):
    e = dict(os.environ, HOME=str(tmp_path / "home"), SCMR_RERUN_HOME=str(tmp_path / "rerun-state"))
    for k in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", viz.ENV_URL, viz.ENV_SAVE_DIR, viz.ENV_RECORDING_ID):
        e.pop(k, None)
    (tmp_path / "home").mkdir()
    return e


def _records(run_dir: Path) -> dict[str, int]:
    return {
        p.parent.name: sum(1 for ln in p.read_text().splitlines() if ln.strip())
        for p in (run_dir / "robots").glob("*/records.jsonl")
    }


@pytest.mark.timeout(240)
def test_up_save_records_every_robot_frame(tmp_path, env, monkeypatch):
    run_dir, rrd = tmp_path / "run", tmp_path / "fleet.rrd"
    before = rerun_processes(env["HOME"])
    res = subprocess.run(scmr("up", *STUB, "--run-dir", str(run_dir), "--save", str(rrd)),
                         env=env, capture_output=True, text=True, timeout=200)
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"scmr view {rrd}" in res.stdout
    monkeypatch.setenv("SCMR_RERUN_HOME", env["SCMR_RERUN_HOME"])
    rows = viz.rrd_rows(rrd)
    per_robot = _records(run_dir)
    assert sorted(per_robot) == ["r1", "r2"] and all(n > 0 for n in per_robot.values())
    for rid, n in per_robot.items():
        assert rows[f"/scmr/robot/{rid}/camera"]["EncodedImage:blob"] == n
        assert rows[f"/scmr/robot/{rid}/camera/drivable"]["SegmentationImage:buffer"] == n
        assert rows[f"/scmr/results/{rid}/tier"]["Scalars:scalars"] == n
        # the robot's own liveliness view of cloud and leader
        assert rows[f"/scmr/alive/cloud/cloud0/{rid}"]["Scalars:scalars"] >= 1
        assert rows[f"/scmr/alive/leader/leader0/{rid}"]["Scalars:scalars"] >= 1
    assert rows["/scmr/fleet/ror"]["Scalars:scalars"] == sum(per_robot.values())
    assert rows["/scmr/alive/cloud/cloud0"]["Scalars:scalars"] >= 1  # the supervisor's view
    report = json.loads((run_dir / "report.json").read_text())
    assert report["requests"] == sum(per_robot.values())
    assert rerun_processes(env["HOME"]) <= before  # the recorder is gone
    assert list((tmp_path / "home").rglob("*")) == []  # analytics: nothing in HOME


@pytest.mark.timeout(240)
def test_up_without_flags_starts_no_rerun(tmp_path, env):
    run_dir = tmp_path / "run"
    before = rerun_processes(env["HOME"])
    res = subprocess.run(scmr("up", *STUB, "--run-dir", str(run_dir)),
                         env=env, capture_output=True, text=True, timeout=200)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "rerun" not in res.stdout + res.stderr
    assert list(tmp_path.rglob("*.rrd")) == []
    assert not (tmp_path / "rerun-state").exists()
    assert rerun_processes(env["HOME"]) <= before
