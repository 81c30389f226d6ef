"""``scmr view --web``: two viewers side by side, a taken port, Ctrl-C (real processes, no screen; ~3 s)."""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from scmr_mesh.mesh.testing import wait_for

pytest.importorskip("rerun")


def _rrd(tmp_path):
    path = tmp_path / "tiny.rrd"
    subprocess.run([sys.executable, "-c", "import rerun as rr\nrr.init('tiny'); rr.save(%r)\n"
                    "rr.log('x', rr.Scalars(1.0))" % str(path)], check=True, timeout=60)
    return path


def _view(rrd, env, *extra):
    # SIGINT ignored, as a script or CI job that starts it in the background leaves it: Python then
    # kept ignoring it and so did rerun (still serving 20 s after SIGINT, before the fix)
    return subprocess.Popen([sys.executable, "-m", "scmr_mesh", "view", str(rrd), "--web", *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))


def _serving(proc, timeout=60.0):
    """Read stderr up to the URL line (rerun logs its own lines first), for at most ``timeout``
    seconds; the URL is printed once the web and gRPC ports answer, so both accept at once.
    Returns (web port, grpc port)."""
    pat = re.compile(r"serving the web viewer on http://127\.0\.0\.1:(\d+)\?url=rerun%2Bhttp%3A%2F%2F127\.0\.0\.1%3A(\d+)%2Fproxy")
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stderr], daemon=True).start()
    seen, m = [], None
    deadline = time.monotonic() + timeout
    while m is None and time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            break
        seen.append(line)
        m = pat.search(line)
    assert m, f"no URL within {timeout:.0f} s: " + "".join(seen)
    web, grpc = int(m.group(1)), int(m.group(2))
    for port in (web, grpc):
        socket.create_connection(("127.0.0.1", port), timeout=5).close()
    return web, grpc


def test_two_web_viewers_run_side_by_side_and_sigint_ends_each(tmp_path):
    env = dict(os.environ, SCMR_RERUN_HOME=str(tmp_path / "rr"))
    rrd = _rrd(tmp_path)
    a = _view(rrd, env)
    b = None
    try:
        ports_a = _serving(a)
        b = _view(rrd, env)  # before: the second took gRPC 9876 too and exited "Address already in use"
        ports_b = _serving(b)
        assert not set(ports_a) & set(ports_b)
        taken = subprocess.run([sys.executable, "-m", "scmr_mesh", "view", str(rrd), "--web", "--port",
                                str(ports_a[1])], capture_output=True, text=True, env=env, timeout=60)
        assert taken.returncode != 0 and f"--port {ports_a[1]} is taken" in taken.stderr
        assert "Traceback" not in taken.stderr
        for p in (a, b):
            os.killpg(p.pid, signal.SIGINT)
            assert p.wait(timeout=15) == 128 + signal.SIGINT
    finally:
        for p in (a, b):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def test_a_killed_viewer_command_leaves_no_rerun_behind(tmp_path):
    """SIGKILL runs no handler: rerun, in its own session, kept serving until the kernel's
    parent-death signal was set for it."""
    env = dict(os.environ, SCMR_RERUN_HOME=str(tmp_path / "rr"))
    p = _view(_rrd(tmp_path), env)
    try:
        web, grpc = _serving(p)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()

    def closed():
        try:
            socket.create_connection(("127.0.0.1", web), timeout=0.2).close()
            return False
        except OSError:
            return True

    wait_for(closed, timeout=30, what=f"rerun to stop serving on {web} after its parent was killed")
