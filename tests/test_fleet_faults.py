"""``scmr up`` tells the truth about its data tier (issue #12, items 1 and 3).

Real fleets (cloud, leader, one robot as processes on loopback, stub pipeline):

* the ODS destroyed during a cloud outage: the restarted cloud never becomes
  ready; the summary says so, the telemetry line is there, the run fails;
* the ODS deleted during the outage: the restarted cloud starts a fresh store,
  the records stored before are lost; the summary and the exit status say so;
* the robot's telemetry queue on a full tmpfs: the refused records are lost in
  ``report.json``, on the console and in the exit status of ``scmr up``.

About 15 s each on a quiet 2-core box.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
from test_data_faults import full_tmpfs
from test_fleet_e2e import STUB, kill_leftovers, scmr

from scmr_mesh.errors import MeshError
from scmr_mesh.fleet import FleetConfig, check_fleet, format_summary
from scmr_mesh.fleet.run import run_fleet
from scmr_mesh.scenario.runner import Hooks

SERVER = ("--process", "scmr_mesh.mesh.testing:stub_process")


def _run_with_damage(run_dir: Path, damage) -> dict:
    """One fleet run; ``damage(run_dir)`` is called right after the cloud was SIGKILLed."""
    cfg = FleetConfig(robots=1, duration_s=6.0, rate_hz=8.0, cloud_outage=(1.5, 3.5), synthetic=["stub"],
                      run_dir=run_dir, server_args=SERVER, workers=1, ready_timeout_s=60)
    cfg.check()
    done = []

    class Damage(Hooks):
        """An engine hook: at the first tick after the crash took effect (the cloud is down)."""

        def tick(self, run) -> None:
            af = run.applied[0]
            if af.start_unix_ns is not None and af.end_unix_ns is None and not done:
                done.append(run.elapsed_s())
                damage(run_dir)

    try:
        rep = run_fleet(cfg, hooks=(Damage(),))
    finally:
        kill_leftovers(run_dir)
    assert done, "the outage never started"
    return rep


def _rm_store(run_dir: Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        (run_dir / f"ods.sqlite{suffix}").unlink(missing_ok=True)


@pytest.mark.timeout(180)
def test_a_restart_that_never_comes_up_fails_the_run(tmp_path):
    def destroy(run_dir: Path) -> None:
        _rm_store(run_dir)
        (run_dir / "ods.sqlite").write_bytes(b"this is no longer a database\n" * 100)

    rep = _run_with_damage(tmp_path / "run", destroy)
    (fault,) = rep["faults"]
    assert fault["end_unix_ns"] is not None and fault["ready_unix_ns"] is None
    text = format_summary(rep)
    assert "NEVER BECAME READY" in text and "restored" not in text
    tel = rep["telemetry"]
    assert "telemetry: " in text and f"{tel['sent']} sent" in text
    # no store can show a record stored: what the robots still hold is queued (safe on their disks), the
    # records the destroyed store had acknowledged are lost
    assert tel["sent"] > 0 and tel["stored"] == 0 and "could not be read" in tel["error"]
    assert tel["queued"] + tel["lost"] == tel["sent"] and tel["queued"] > 0 and tel["lost"] > 0, tel
    assert any("never became ready" in p for p in rep["problems"])
    assert rep["ror"] == 1.0  # every request was answered (the leader): only the data tier failed
    with pytest.raises(MeshError, match="never became ready"):
        check_fleet(rep, 1.0)
    assert json.loads((tmp_path / "run" / "report.json").read_text())["problems"] == rep["problems"]


@pytest.mark.timeout(180)
def test_records_lost_with_the_store_show_on_the_console_and_fail_the_run(tmp_path):
    rep = _run_with_damage(tmp_path / "run", _rm_store)
    (fault,) = rep["faults"]
    assert fault["ready_unix_ns"] is not None  # the restarted cloud started a fresh store
    tel = rep["telemetry"]
    assert tel["lost"] > 0 and tel["stored"] == tel["sent"] - tel["lost"] and "error" not in tel
    text = format_summary(rep)
    assert f"{tel['lost']} lost" in text and f"PROBLEM: {tel['lost']} of {tel['sent']} telemetry records lost" in text
    with pytest.raises(MeshError, match="telemetry records lost"):
        check_fleet(rep, 1.0)


@pytest.mark.timeout(180)
@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_scmr_up_with_a_full_disk_delivers_telemetry_from_memory(tmp_path):
    """Issue 25 item 2: the robot's queue on a full tmpfs, the cloud up all along: nothing is lost.

    Before, every record the disk refused was counted lost (exit 1); now it is sent from the robot's
    memory buffer and stored, and the console still says the disk refused them.
    """
    run_dir = tmp_path / "run"
    with full_tmpfs(tmp_path / "mnt", free_pages=3):
        try:
            r = subprocess.run(
                scmr("up", "--robots", "1", "--duration", "5", "--rate", "20", "--run-dir", str(run_dir),
                     f"--robot-arg=--telemetry-queue={tmp_path / 'mnt' / 'q'}", *STUB),
                capture_output=True, text=True, timeout=150)
        finally:
            kill_leftovers(run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((run_dir / "report.json").read_text())
    tel = rep["telemetry"]
    assert tel["refused"] > 0 and tel["sent"] > tel["refused"]
    assert tel["lost"] == 0 and tel["stored"] == tel["sent"], tel
    assert f"0 lost ({tel['refused']} refused by the robots' disks)" in r.stdout
    s = json.loads((run_dir / "robots" / "r1" / "telemetry.json").read_text())
    assert s["memory"]["delivered"] == s["refused"] and s["dropped"] == 0 and s["lost"] == 0
    assert rep["peers"]["r1"]["exit"] == 0 and "Traceback" not in r.stderr
    assert rep["ror"] == 1.0
