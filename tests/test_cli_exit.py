"""``scmr`` leaves without the interpreter's finalization (cli._exit_now).

Before Python 3.14 a thread that takes the GIL once finalization has begun is ended with
``pthread_exit``; through zenoh's Rust frames that aborts the process ("FATAL: exception not
rethrown", status -6) after its work is done.  A robot of the suite died so once (fc55).  The child
below keeps 8 daemon threads in ``Subscriber.recv()`` while samples keep arriving: with a plain
``sys.exit(0)`` it aborted in 16 of 20 runs here, with ``_exit_now(0)`` in 0 of 20
(docs/ZENOH.md section 21).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

CHILD = textwrap.dedent("""
    import atexit, sys, threading, time
    import zenoh
    from scmr_mesh.cli import _exit_now

    conf = zenoh.Config.from_json5('{mode: "peer", scouting: {multicast: {enabled: false}, '
                                   'gossip: {enabled: false}}, listen: {endpoints: []}}')
    s = zenoh.open(conf)
    subs = [s.declare_subscriber("scmr-test/exit") for _ in range(8)]
    pub = s.declare_publisher("scmr-test/exit")

    def reader(sub):
        while True:
            sub.recv()  # blocks with the GIL released, in zenoh's Rust code

    def writer():
        while True:
            pub.put(b"x")

    for sub in subs:
        threading.Thread(target=reader, args=(sub,), daemon=True).start()
    threading.Thread(target=writer, daemon=True).start()
    probe = s.declare_subscriber("scmr-test/exit")
    for _ in range(100):  # samples flow: the readers are busy in recv()
        probe.recv()
    atexit.register(lambda: print("atexit ran", flush=True))
    print("work done")  # buffered: _exit_now must flush it
    _exit_now(0)
""")


def test_exit_with_zenoh_threads_busy_is_clean_and_runs_atexit():
    for _ in range(3):
        r = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
        assert r.stdout.splitlines() == ["work done", "atexit ran"], r.stdout
        assert "FATAL" not in r.stderr, r.stderr


def test_the_program_entry_points_exit_through_exit_now():
    """The console script and ``python -m scmr_mesh`` both go through ``run``; a usage error keeps
    its status and message."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    assert 'scmr = "scmr_mesh.cli:run"' in (root / "pyproject.toml").read_text()
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "robot", "--no-such-flag"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "scmr robot: error:" in r.stderr, (r.returncode, r.stderr)
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("scmr-mesh "), (r.returncode, r.stdout)
