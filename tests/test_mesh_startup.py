"""A service's start-up: the phases it reports, and what it no longer repeats.

No wall-clock thresholds here: ``scmr bench mesh`` and docs/BENCHMARKS.md
measure the cold start; these tests check that the phases are measured and
reported, and that warm-up work happens once.
"""

from __future__ import annotations

import json
import os
import time

import pytest
from conftest import free_port

from scmr_mesh.mesh.startup import StartupClock, exec_age_s, process_cpu_ms
from scmr_mesh.mesh.testing import spawn_peer, stop_peer, wait_for

PHASES = ["interpreter", "command line", "zenoh config", "data process forked", "pipeline imports", "kernels + warm-up run",
          "worker pool", "wire validators", "setup hooks", "zenoh session", "queryables", "warm-up query", "token"]


def test_clock_phases_add_up_and_start_at_exec():
    assert exec_age_s() is not None and exec_age_s() > 0
    clock = StartupClock()
    clock.mark("a")
    sum(range(200_000))  # some CPU
    clock.mark("b", note="x")
    d = clock.as_dict()
    assert d["since_exec"] is True
    assert [p["phase"] for p in d["phases"]] == ["a", "b"] and d["phases"][1]["note"] == "x"
    # the first phase runs from exec, so it holds this interpreter's whole life so far
    assert d["phases"][0]["cpu_ms"] > 0 and d["phases"][1]["cpu_ms"] > 0
    assert d["wall_ms"] == pytest.approx(sum(p["wall_ms"] for p in d["phases"]), abs=0.2)
    text = clock.format()
    assert "total from exec" in text and "(note x)" in text


def test_process_cpu_of_another_process():
    assert process_cpu_ms(os.getpid()) > 0
    assert process_cpu_ms(2**22 + 12345) is None


def test_cloud_reports_its_start_up_phases(tmp_path):
    ready = tmp_path / "c1.ready"
    log = tmp_path / "c1.log"
    p = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", f"tcp/127.0.0.1:{free_port()}", "--workers", "2",
                    "--ready-file", str(ready), "--verbose", "--data-process", "on"], log_path=log)
    try:
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=120, what="cloud ready")
        assert p.poll() is None, log.read_text()
        info = json.loads(ready.read_text())
        st = info["startup"]
        assert [ph["phase"] for ph in st["phases"]] == PHASES
        assert st["since_exec"] is True
        assert all(ph["wall_ms"] >= 0 and ph["cpu_ms"] >= 0 for ph in st["phases"])
        assert st["wall_ms"] >= max(ph["wall_ms"] for ph in st["phases"])
        kernels = next(ph for ph in st["phases"] if ph["phase"] == "kernels + warm-up run")["kernels"]
        assert kernels.startswith(("aot ", "jit ("))
        assert len(info["workers"]) == 2
        wait_for(lambda: "total from exec" in log.read_text(), timeout=10, what="the phase table in the log")
        text = log.read_text()
        assert "warm-up query" in text and "cpu ms" in text
    finally:
        stop_peer(p)


COUNT_DIR = "SCMR_TEST_WARM_DIR"


def counted_process(image: bytes, *, encoding: str, shape, mode: str = "best") -> dict:
    from scmr_mesh.mesh.testing import stub_process

    return stub_process(image, encoding=encoding, shape=shape, mode=mode)


def _count_warm() -> None:
    d = os.environ[COUNT_DIR]
    with open(os.path.join(d, f"{os.getpid()}.{time.monotonic_ns()}"), "w"):
        pass


counted_process.warm_up = _count_warm  # type: ignore[attr-defined]


def test_forked_workers_are_not_warmed_again(tmp_path, monkeypatch):
    # the service warms the process function once, then forks its workers from
    # that warm state; warming each worker again cost 2 x 30 ms of CPU at start
    from scmr_mesh.mesh.work import WorkerPool

    monkeypatch.setenv(COUNT_DIR, str(tmp_path))
    pool = WorkerPool(2, process="test_mesh_startup:counted_process")
    try:
        pids = pool.start()
        assert len(pids) == 2
        assert len(list(tmp_path.iterdir())) == 1
        assert list(tmp_path.iterdir())[0].name.startswith(f"{os.getpid()}.")
    finally:
        pool.shutdown()
