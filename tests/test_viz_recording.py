"""Recordings read back: a fleet process and two robot processes log into one
recording through the --save sink; the file holds the expected entities and
one frame per request per robot.  Also ``scmr view`` on it, and analytics off.

Runs real processes (a ``rerun --save`` recorder and two robot loggers); about
10 s on a 2-core machine.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from scmr_mesh import cli, viz

N = 8  # requests per robot; request 5 fails
FAILED = {5}

ROBOT = r"""
import argparse, sys, time
import numpy as np
from scmr_mesh import viz
p = argparse.ArgumentParser()
p.add_argument("robot"); p.add_argument("n", type=int)
viz.add_rerun_peer_args(p)
a = p.parse_args()
rv = viz.RobotViz(viz.RerunOptions.from_args(a), a.robot)
rng = np.random.default_rng(len(a.robot))
for i in range(a.n):
    rgb = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    mask = np.zeros((225, 300), np.uint8); mask[120:, 60:240] = 255
    ok = i not in (5,)
    now = time.time_ns()
    rv.observe({"robot": a.robot, "seq": i, "ok": ok, "tier": "cloud" if i < 4 else "leader",
                "tor_ms": 2.0 + i, "served_by": "c0", "sent_unix_ns": now - 2_000_000,
                "received_unix_ns": now, "energy_j": 0.5, "battery": 1.0 - i / 100,
                "error": None if ok else "timeout"}, rgb, mask, srm=rgb)
rv.close()
"""


@pytest.fixture(scope="module")
def isolated_env(tmp_path_factory):
    """HOME and the rerun state dir in temporary folders (nothing in the real home)."""
    root = tmp_path_factory.mktemp("rerun-env")
    mp = pytest.MonkeyPatch()
    mp.setenv("HOME", str(root / "home"))
    mp.setenv("SCMR_RERUN_HOME", str(root / "state"))
    for var in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME", "CI"):
        mp.delenv(var, raising=False)
    (root / "home").mkdir()
    yield root
    mp.undo()


@pytest.fixture(scope="module")
def fleet_recording(isolated_env):
    out = isolated_env / "run.rrd"
    fv = viz.FleetViz(viz.RerunOptions("save", str(out)), robots=["r0", "r1"])
    procs = []
    try:
        t0 = time.time_ns()
        both = {("cloud", "cloud0"): True, ("leader", "leader0"): True}
        fv.update(alive=both, t_unix_ns=t0)
        procs = [
            subprocess.Popen([sys.executable, "-c", ROBOT, r, str(N), *fv.child_args()], start_new_session=True)
            for r in ("r0", "r1")
        ]
        # a supervisor calls update() every tick: only changes and news are logged
        fault = {"kind": "crash", "target": "cloud0", "tier": "cloud", "start_unix_ns": t0 + 10**8, "end_unix_ns": None}
        fv.update(alive=both, faults=[fault], t_unix_ns=t0 + 10**7)
        fv.update(alive={**both, ("cloud", "cloud0"): False}, faults=[fault], t_unix_ns=t0 + 10**8)
        fault["end_unix_ns"] = t0 + 3 * 10**8
        fv.update(alive={**both, ("cloud", "cloud0"): False}, faults=[fault], t_unix_ns=t0 + 3 * 10**8)
        fv.update(alive=both, faults=[fault], t_unix_ns=t0 + 4 * 10**8)
        fv.update(records=[{"ok": i % N not in FAILED, "received_unix_ns": t0 + i} for i in range(2 * N)])
        codes = [p.wait(timeout=120) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, 9)
                p.wait()
        path = fv.close()
    assert codes == [0, 0]
    return fv, path


def test_save_writes_one_finalised_file(fleet_recording):
    fv, path = fleet_recording
    assert path is not None and path.is_file()
    assert sorted(p.name for p in path.parent.glob("run*")) == ["run.rrd"]  # no .partial left
    assert fv._sink.proc.poll() is not None  # the recorder process is gone
    res = viz.run_rerun_cli(["rrd", "verify", str(path)])
    assert res.returncode == 0, res.stderr


def test_all_processes_share_one_recording(fleet_recording):
    fv, path = fleet_recording
    text = viz.run_rerun_cli(["rrd", "print", str(path)]).stdout
    recordings = set(re.findall(r'Recording,\s*"([^"]+)",\s*"([^"]+)"', text))
    assert recordings == {(viz.APP_ID, fv.recording_id)}
    assert re.search(r"Blueprint,\s*\"scmr-mesh\"", text), "the blueprint is saved with the recording"


def test_expected_entities_and_frames_per_robot(fleet_recording):
    _, path = fleet_recording
    rows = viz.rrd_rows(path)
    assert rows["/scmr/robot"]["AnnotationContext:context"] >= 1
    ok = N - len(FAILED)
    for r in ("r0", "r1"):
        assert rows[f"/scmr/robot/{r}/camera"]["EncodedImage:blob"] == N
        assert rows[f"/scmr/robot/{r}/camera/drivable"]["SegmentationImage:buffer"] == N
        assert rows[f"/scmr/robot/{r}/srm"]["EncodedImage:blob"] == N
        assert rows[f"/scmr/results/{r}/tor_ms"]["Scalars:scalars"] == ok  # failed requests have no ToR
        assert rows[f"/scmr/results/{r}/tier"]["Scalars:scalars"] == N
        assert rows[f"/scmr/results/{r}/ror"]["Scalars:scalars"] == N
        assert rows[f"/scmr/results/{r}/log"]["TextLog:text"] == N
        assert rows[f"/scmr/telemetry/{r}/battery"]["Scalars:scalars"] == N
        assert rows[f"/scmr/telemetry/{r}/energy_j"]["Scalars:scalars"] == N
    assert rows["/scmr/alive/cloud/cloud0"]["Scalars:scalars"] == 3
    assert rows["/scmr/alive/leader/leader0"]["Scalars:scalars"] == 1
    # 0 at the run's start, just before, 1 at start, 0 at end, 0 at the run's end (the axis spans the run)
    assert rows["/scmr/faults/cloud0"]["Scalars:scalars"] == 5
    assert rows["/scmr/faults/log"]["TextLog:text"] == 2
    assert rows["/scmr/fleet/ror"]["Scalars:scalars"] == 2 * N


def test_nothing_written_to_home(fleet_recording, isolated_env):
    assert list((isolated_env / "home").rglob("*")) == []
    cfg = json.loads((isolated_env / "state" / "config" / "rerun" / "analytics.json").read_text())
    assert cfg["analytics_enabled"] is False


def test_analytics_oracle_detects_a_plain_rerun_run(isolated_env, tmp_path):
    """Control: the same CLI call without rerun_env() does write analytics to HOME."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("XDG_") and k != "CI"}
    env["HOME"] = str(home)
    subprocess.run([viz.rerun_executable(), "--version"], env=env, capture_output=True, timeout=60)
    cfg = home / ".config" / "rerun" / "analytics.json"
    assert cfg.is_file() and json.loads(cfg.read_text())["analytics_enabled"] is True
    # ... and with rerun_env() the user's HOME stays empty
    home2 = tmp_path / "home2"
    home2.mkdir()
    env2 = viz.rerun_env(dict(env, HOME=str(home2)))
    subprocess.run([viz.rerun_executable(), "--version"], env=env2, capture_output=True, timeout=60)
    assert list(home2.rglob("*")) == []


def test_image_every_thins_images_not_scalars(isolated_env):
    out = isolated_env / "r9.rrd"
    rv = viz.RobotViz(viz.RerunOptions("save", str(out)), "r9", image_every=3)
    for i in range(10):
        rv.observe({"seq": i, "ok": True, "tier": "local", "tor_ms": 1.0}, np.zeros((10, 12, 3), np.uint8), np.ones((10, 12), bool))
    rv.log_liveliness("cloud", "c0", True)
    rv.log_liveliness("cloud", "c0", False)
    rv.log_liveliness("robot", "r2", True)  # other robots' tokens are not plotted
    rv.close()
    rows = viz.rrd_rows(out)
    assert rows["/scmr/alive/cloud/c0/r9"]["Scalars:scalars"] == 2
    assert not any(k.startswith("/scmr/alive/robot") for k in rows)
    assert rows["/scmr/robot/r9/camera"]["EncodedImage:blob"] == 4  # requests 0, 3, 6, 9
    assert rows["/scmr/robot/r9/camera/drivable"]["SegmentationImage:buffer"] == 4
    assert rows["/scmr/results/r9/tor_ms"]["Scalars:scalars"] == 10


# -- scmr view --------------------------------------------------------------


def test_view_summary_lists_entities(fleet_recording, capsys):
    _, path = fleet_recording
    assert cli.main(["view", str(path), "--summary"]) == 0
    out = capsys.readouterr().out
    assert "/scmr/robot/r0/camera/drivable" in out and f"SegmentationImage:buffer={N}" in out


@pytest.mark.parametrize("content", [None, b"", b"not a recording"])
def test_view_rejects_missing_or_invalid_file(tmp_path, capsys, content):
    f = tmp_path / "x.rrd"
    if content is not None:
        f.write_bytes(content)
    assert cli.main(["view", str(f)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scmr: error:") and "x.rrd" in err[0]


def test_view_without_display_says_what_to_do(fleet_recording, capsys, monkeypatch):
    _, path = fleet_recording
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli.main(["view", str(path)]) == 1
    assert "--web" in capsys.readouterr().err


def test_peers_in_isolated_namespaces_save_files_that_are_merged(isolated_env):
    """The scenario path: peers get only the environment, save their own file, merged at close."""
    out = isolated_env / "scenario.rrd"
    save_dir = isolated_env / "peer-files"
    code = (
        "import argparse, numpy as np\n"
        "from scmr_mesh import viz\n"
        "p = argparse.ArgumentParser(); viz.add_rerun_peer_args(p)\n"
        "rv = viz.robot_viz(viz.RerunOptions.for_peer(p.parse_args([]), 'r7'), 'r7')\n"
        "for i in range(3):\n"
        "    rv.observe({'seq': i, 'ok': True, 'tier': 'leader', 'tor_ms': 1.0},"
        " np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), bool))\n"
        "rv.close()\n"
    )
    with viz.peers_env_session(viz.RerunOptions("save", str(out)), robots=["r7"], save_dir=save_dir) as fv:
        assert os.environ[viz.ENV_SAVE_DIR] == str(save_dir)
        subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
        fv.update(faults=[{"kind": "partition", "target": "cloud | r7", "start_unix_ns": time.time_ns()}])
    assert viz.ENV_SAVE_DIR not in os.environ
    assert len(list(save_dir.glob("r7-*.rrd"))) == 1
    rows = viz.rrd_rows(out)
    assert rows["/scmr/robot/r7/camera/drivable"]["SegmentationImage:buffer"] == 3
    assert "/scmr/faults/cloud_r7" in rows
    text = viz.run_rerun_cli(["rrd", "print", str(out)]).stdout
    assert set(re.findall(r'Recording,\s*"([^"]+)",\s*"([^"]+)"', text)) == {(viz.APP_ID, fv.recording_id)}


def test_serve_starts_a_web_viewer_that_peers_reach_and_stops_it(isolated_env):
    import urllib.request

    from conftest import free_port

    fv = viz.FleetViz(viz.RerunOptions("serve"), robots=["r0"], port=free_port(), web_port=free_port())
    proc = fv._sink.proc
    try:
        assert fv.hint.startswith("rerun web viewer: http://127.0.0.1:")
        with urllib.request.urlopen(fv._sink.web_url.split("?")[0], timeout=10) as resp:
            assert resp.status == 200 and "html" in resp.headers.get("content-type", "")
        rv = viz.RobotViz(viz.RerunOptions("connect", fv.url, fv.recording_id), "r0")
        rv.close()
    finally:
        assert fv.close() is None
    assert proc.poll() is not None  # the server does not outlive the command


def test_serve_waits_for_the_web_port_before_it_prints_the_url(isolated_env, tmp_path, monkeypatch):
    """rerun opens its gRPC port before its web port: the sink waits for both, so the URL it prints
    answers.  A fake rerun that opens only the gRPC port and exits once probed is refused."""
    from conftest import free_port

    fake = tmp_path / "rerun"
    fake.write_text(
        f"#!{sys.executable}\n"
        "import socket, sys\n"
        "port = int(sys.argv[sys.argv.index('--port') + 1])\n"
        "s = socket.socket(); s.bind(('127.0.0.1', port)); s.listen(4)\n"
        "s.accept()\n"
        "sys.stderr.write('web viewer failed to start\\n'); sys.exit(3)\n"
    )
    fake.chmod(0o755)
    monkeypatch.setenv("RERUN_CLI_PATH", str(fake))
    web = free_port()
    with pytest.raises(viz.ViewerError, match=rf"exited with status 3 before listening on port {web}.*web viewer failed"):
        viz.FleetViz(viz.RerunOptions("serve"), robots=["r0"], port=free_port(), web_port=web)


def test_serve_refuses_a_web_port_another_server_holds(isolated_env):
    """Another server on the web port would answer the wait for rerun's: refused, in one line."""
    import socket

    from conftest import free_port

    with socket.socket() as other:
        other.bind(("127.0.0.1", free_port()))
        other.listen(1)
        web = other.getsockname()[1]
        with pytest.raises(viz.ViewerError, match=rf"^--serve: the web viewer port {web} is taken"):
            viz.FleetViz(viz.RerunOptions("serve"), robots=["r0"], port=free_port(), web_port=web)


SINK_THEN_WAIT = r"""
import signal, sys, threading
from scmr_mesh import viz
mode, out, port, web, ignore = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1"
if ignore:   # started with SIGTERM ignored (`trap '' TERM`, some supervisors): rerun inherited that
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
if mode == "save":
    fv = viz.FleetViz(viz.RerunOptions("save", out), robots=["r0"], port=port)
else:
    fv = viz.FleetViz(viz.RerunOptions("serve"), robots=["r0"], port=port, web_port=web)
print(fv._sink.proc.pid, flush=True)
threading.Event().wait()
"""


@pytest.mark.parametrize("mode, ignore", [("save", False), ("serve", False), ("save", True)],
                         ids=["save", "serve", "save-with-SIGTERM-ignored"])
def test_a_killed_fleet_leaves_no_recorder_or_web_viewer_behind(isolated_env, tmp_path, mode, ignore):
    """SIGKILL runs no handler: the fleet's `rerun --save` recorder and `rerun --serve-web` viewer,
    in their own sessions, kept running (recording, holding their ports) until the sink set the
    kernel's parent-death signal for them; now they stop with the fleet, also when the fleet was
    started with SIGTERM ignored (rerun inherited that and ignored its death signal, a review found)."""
    import select

    from conftest import free_port
    from scmr_mesh.mesh.testing import wait_for

    port, web = free_port(), free_port()
    p = subprocess.Popen([sys.executable, "-c", SINK_THEN_WAIT, mode, str(tmp_path / "run.rrd"), str(port), str(web),
                          "1" if ignore else "0"], stdout=subprocess.PIPE, text=True)
    rerun_pid = None
    try:
        ready, _, _ = select.select([p.stdout], [], [], 60)
        assert ready, "the fleet process printed no rerun pid within 60 s"
        rerun_pid = int(p.stdout.readline())
    finally:
        p.kill()
        p.wait()

    def gone():
        try:
            with open(f"/proc/{rerun_pid}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] == "Z"
        except OSError:
            return True

    try:
        wait_for(gone, timeout=30, what=f"rerun ({mode}, pid {rerun_pid}) to stop after the fleet was killed")
    finally:   # a failure must not leave rerun holding its ports for the rest of the suite
        if not gone():
            os.kill(rerun_pid, 9)


def test_spawn_without_display_fails_fast(isolated_env, monkeypatch):
    from conftest import free_port

    monkeypatch.setattr("scmr_mesh.viz.sink.has_display", lambda: False)
    with pytest.raises(viz.ViewerError, match="--serve"):
        viz.FleetViz(viz.RerunOptions("spawn"), robots=["r0"], port=free_port())


# -- off the request thread ---------------------------------------------------

def test_observe_logs_nothing_on_the_callers_thread(isolated_env):
    import threading

    from scmr_mesh.mesh.testing import wait_for

    out = isolated_env / "r7.rrd"
    rv = viz.RobotViz(viz.RerunOptions("save", str(out)), "r7", batch_s=0.05)
    threads = []
    rec, rr = rv._stream.rec, rv._stream.rr
    real_log, real_send = rec.log, rr.send_columns

    def log(*a, **k):
        threads.append(threading.current_thread().name)
        return real_log(*a, **k)

    class RR:
        def __getattr__(self, name):
            return getattr(rr, name)

        def send_columns(self, *a, **k):
            threads.append(threading.current_thread().name)
            return real_send(*a, **k)

    rec.log, rv._stream.rr = log, RR()
    rgb = np.zeros((10, 12, 3), np.uint8)
    for i in range(5):
        rv.observe({"seq": i, "ok": True, "tier": "cloud", "tor_ms": 3.0, "battery": 0.9}, rgb, np.ones((10, 12), bool))
        rv.log_telemetry(battery=0.9)
    rv.log_liveliness("cloud", "c0", True)
    assert "MainThread" not in threads
    wait_for(lambda: threads.count("scmr-rerun") >= 5 + 6, timeout=30, what="the logger thread to log the batch")
    assert set(threads) == {"scmr-rerun"}
    rv.close()
    rows = viz.rrd_rows(out)
    assert rows["/scmr/results/r7/tor_ms"]["Scalars:scalars"] == 5
    assert rows["/scmr/results/r7/log"]["TextLog:text"] == 5
    assert rows["/scmr/telemetry/r7/battery"]["Scalars:scalars"] == 10
    assert rows["/scmr/robot/r7/camera"]["EncodedImage:blob"] == 5
    assert rows["/scmr/alive/cloud/c0/r7"]["Scalars:scalars"] == 1


def test_images_beyond_the_queue_limit_are_dropped_and_counted(isolated_env):
    out = isolated_env / "r8.rrd"
    rv = viz.RobotViz(viz.RerunOptions("save", str(out)), "r8", batch_s=3600, max_images=2)
    for i in range(5):
        rv.observe({"seq": i, "ok": i != 3, "tier": "leader", "tor_ms": 1.0}, np.zeros((10, 12, 3), np.uint8))
    assert rv.dropped_images == 3
    rv.close()
    rows = viz.rrd_rows(out)
    assert rows["/scmr/robot/r8/camera"]["EncodedImage:blob"] == 2
    assert rows["/scmr/results/r8/tier"]["Scalars:scalars"] == 5
    assert rows["/scmr/results/r8/tor_ms"]["Scalars:scalars"] == 4


def test_the_faults_plot_spans_the_whole_run_not_only_the_faults():
    """The faults series held points only around each fault, so the plot's time axis (fitted to
    its data) covered ~3 s of a 20 s run; each fault's line now runs from the run's start to its end."""
    import threading
    import types

    from scmr_mesh.viz.recording import _Viz

    logged = []

    class Stream:
        _lock = threading.Lock()
        rr = types.SimpleNamespace(Scalars=lambda v: ("scalar", v), SeriesLines=lambda **k: ("series",),
                                   TextLog=lambda *a, **k: ("text",))
        t = None

        def at(self, t):
            self.t = t

        rec = None

    stream = Stream()
    stream.rec = types.SimpleNamespace(log=lambda entity, x, static=False: logged.append((stream.t, entity, x)))
    v = _Viz()
    v._stream, v._alive, v._faults, v._last_alive = stream, {}, {}, {}
    s = 1_000_000_000
    v._t_first = 100 * s
    fault = {"kind": "crash", "target": "cloud", "start_unix_ns": 104 * s}
    v.update(faults=[fault])
    v.update(faults=[dict(fault, end_unix_ns=107 * s)])
    v.update(faults=[dict(fault, end_unix_ns=107 * s)])  # repeated ticks log nothing new
    v._end_faults()
    pts = [(t, x[1]) for t, e, x in logged if e.endswith("/faults/cloud") and x[0] == "scalar"]
    assert pts[0] == (100 * s, 0.0) and pts[-1][1] == 0.0 and pts[-1][0] > 107 * s
    assert (104 * s, 1.0) in pts and (107 * s, 0.0) in pts and len(pts) == len(set(pts)) == 5
