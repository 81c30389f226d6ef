"""The process supervisor with small dummy children (no middleware). ~6 s."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from scmr_mesh.errors import MeshError
from scmr_mesh.fleet.procs import PeerSpec, Supervisor, log_tail

# A dummy peer: optional grandchild, prints its pid, writes the ready file, obeys SIGTERM.
DUMMY = textwrap.dedent("""
    import os, pathlib, signal, subprocess, sys, time
    ready, mode = sys.argv[1], sys.argv[2]
    if mode == "fail":
        print("boom: cannot bind", flush=True); sys.exit(3)
    if mode == "ignore-term":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    else:
        signal.signal(signal.SIGTERM, lambda *a: sys.exit(0))
    if mode == "grandchild":
        g = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        print("grandchild", g.pid, flush=True)
    print("pid", os.getpid(), flush=True)
    if mode != "never-ready":
        pathlib.Path(ready).touch()
    time.sleep(60)
""")


def spec(tmp_path: Path, name: str, mode: str = "ok") -> PeerSpec:
    script = tmp_path / "dummy.py"
    script.write_text(DUMMY)
    ready = tmp_path / f"{name}.ready"
    return PeerSpec(name, [sys.executable, str(script), str(ready), mode],
                    log_path=tmp_path / "logs" / f"{name}.log", ready_file=ready)


def gone(pid: int) -> bool:
    """True if ``pid`` no longer runs (absent or a zombie)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def wait_gone(pids, timeout=5.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        left = [p for p in pids if not gone(p)]
        if not left:
            return []
        time.sleep(0.05)
    return [p for p in pids if not gone(p)]


def test_clean_stop_and_logs(tmp_path):
    with Supervisor(term_timeout=5) as sup:
        for n in ("a", "b"):
            sup.start(spec(tmp_path, n))
        sup.wait_ready(["a", "b"], timeout=20)
        pids = [sup.procs[n].pid for n in ("a", "b")]
        assert all(sup.procs[n].ready_unix_ns >= sup.procs[n].started_unix_ns for n in ("a", "b"))
        # each child leads its own process group
        assert all(os.getpgid(p) == p for p in pids)
        assert sup.stop_all() == {"a": 0, "b": 0}
    assert wait_gone(pids) == []
    assert f"pid {pids[0]}" in (tmp_path / "logs" / "a.log").read_text()


def test_sigterm_ignored_then_sigkill(tmp_path):
    sup = Supervisor(term_timeout=0.5)
    try:
        sup.start(spec(tmp_path, "stubborn", "ignore-term"))
        sup.wait_ready(["stubborn"], timeout=20)
        assert sup.stop_all() == {"stubborn": -signal.SIGKILL}
        sigs = [s for s, _ in sup.procs["stubborn"].signalled]
        assert sigs == [signal.SIGTERM, signal.SIGKILL]
    finally:
        sup.stop_all(timeout=0)


def test_kill_and_restart(tmp_path):
    with Supervisor() as sup:
        p1 = sup.start(spec(tmp_path, "cloud"))
        sup.wait_ready(["cloud"], timeout=20)
        t_kill = sup.kill("cloud")
        assert p1.popen.returncode == -signal.SIGKILL and t_kill >= p1.ready_unix_ns
        assert sup.exited() == {"cloud": -signal.SIGKILL}
        p2 = sup.restart("cloud")
        assert p2.pid != p1.pid and p2.started_unix_ns >= t_kill
        assert p2.ready_unix_ns is None  # the stale ready file was removed before the restart
        sup.wait_ready(["cloud"], timeout=20)
        assert sup.exited() == {}
    text = (tmp_path / "logs" / "cloud.log").read_text()
    assert text.count("=== cloud starting") == 2  # one log, both lives


def test_group_is_killed_with_its_leader(tmp_path):
    with Supervisor(term_timeout=5) as sup:
        sup.start(spec(tmp_path, "g", "grandchild"))
        sup.wait_ready(["g"], timeout=20)
        line = next(ln for ln in (tmp_path / "logs" / "g.log").read_text().splitlines()
                    if ln.startswith("grandchild"))
        grandchild = int(line.split()[1])
        assert not gone(grandchild)
        sup.stop_all()
    assert wait_gone([grandchild]) == []


def test_startup_failure_names_peer_and_shows_log_tail(tmp_path):
    with Supervisor() as sup:
        sup.start(spec(tmp_path, "cloud", "fail"))
        with pytest.raises(MeshError, match=r"(?s)'cloud' exited with status 3.*boom: cannot bind") as e:
            sup.wait_ready(["cloud"], timeout=20)
        assert str(tmp_path / "logs" / "cloud.log") in str(e.value)


def test_startup_timeout_names_peer_and_ready_file(tmp_path):
    with Supervisor(term_timeout=2) as sup:
        sup.start(spec(tmp_path, "slow", "never-ready"))
        with pytest.raises(MeshError, match=r"(?s)'slow' was not ready within 0.5 s.*slow.ready.*\n.*pid \d+"):
            sup.wait_ready(["slow"], timeout=0.5)


def test_unknown_peer_and_double_start(tmp_path):
    with Supervisor() as sup:
        with pytest.raises(MeshError, match="no peer named 'x'"):
            sup.kill("x")
        sup.start(spec(tmp_path, "a"))
        with pytest.raises(MeshError, match="already running"):
            sup.start(spec(tmp_path, "a"))


def test_log_tail(tmp_path):
    f = tmp_path / "x.log"
    f.write_text("".join(f"line {i}\n" for i in range(100)))
    assert log_tail(f, 3).split() == ["line", "97", "line", "98", "line", "99"]
    assert "no log" in log_tail(tmp_path / "missing.log")


def test_no_orphans_when_the_supervisor_is_sigkilled(tmp_path):
    """SIGKILL the supervising process: PR_SET_PDEATHSIG takes its children down."""
    pidfile = tmp_path / "pids.json"
    parent = textwrap.dedent(f"""
        import json, os, sys, time
        from pathlib import Path
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_procs import spec
        from scmr_mesh.fleet.procs import Supervisor
        tmp = Path({str(tmp_path)!r})
        sup = Supervisor()
        for n in ("cloud", "leader", "r0"):
            sup.start(spec(tmp, n))
        sup.wait_ready(["cloud", "leader", "r0"], timeout=20)
        # written whole, then renamed: the test never reads a half-written file
        Path({str(pidfile)!r} + ".tmp").write_text(json.dumps([p.pid for p in sup.procs.values()]))
        os.replace({str(pidfile)!r} + ".tmp", {str(pidfile)!r})
        time.sleep(60)
    """)
    p = subprocess.Popen([sys.executable, "-c", parent], start_new_session=True)
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 30
        while not pidfile.exists() and time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.05)
        assert pidfile.exists(), "the supervising process did not start its children"
        pids = json.loads(pidfile.read_text())
        assert len(pids) == 3 and not any(gone(x) for x in pids)
        p.kill()
        p.wait()
        assert wait_gone(pids) == []
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        for x in pids:
            try:
                os.killpg(x, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_ready_time_is_when_the_peer_wrote_its_ready_file(tmp_path):
    # the supervisor polls; the failback split (restart -> ready -> first answer) needs the
    # moment the peer was ready, which it writes into the file as t_unix_ns
    code = ("import json, pathlib, sys, time\n"
            "pathlib.Path(sys.argv[1]).write_text(json.dumps({'t_unix_ns': 1234567890123456789}))\n"
            "time.sleep(60)\n")
    ready = tmp_path / "p.ready"
    s = PeerSpec("p", [sys.executable, "-c", code, str(ready)], log_path=tmp_path / "p.log", ready_file=ready)
    with Supervisor() as sup:
        sup.start(s)
        sup.wait_ready(["p"], timeout=30)
        assert sup.procs["p"].ready_unix_ns == 1234567890123456789
        sup.stop_all()


def test_signals_to_interrupt_keeps_ignored_signals_and_works_off_the_main_thread():
    """nohup's ignored SIGHUP stays ignored (a bench kept running after a logout); from another
    thread nothing changes instead of 'signal only works in main thread'; after the first
    SIGTERM a second one cannot cut the clean-up short."""
    import threading

    from scmr_mesh.fleet.procs import signals_to_interrupt

    old_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        cleaned = []
        with pytest.raises(KeyboardInterrupt):
            with signals_to_interrupt():
                assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
                try:
                    signal.raise_signal(signal.SIGTERM)  # its Python handler runs before this call returns
                    pytest.fail("SIGTERM did not interrupt the block")
                finally:
                    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN  # during the clean-up
                    signal.raise_signal(signal.SIGTERM)  # ignored: the clean-up goes on
                    cleaned.append(True)
        assert cleaned
        assert signal.getsignal(signal.SIGTERM) is old_term and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN

        errors = []

        def off_main():
            try:
                with signals_to_interrupt():
                    pass
            except Exception as exc:  # pragma: no cover - the failure this guards against
                errors.append(exc)

        t = threading.Thread(target=off_main)
        t.start()
        t.join()
        assert errors == []
    finally:
        signal.signal(signal.SIGHUP, old_hup)
