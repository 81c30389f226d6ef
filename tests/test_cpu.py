"""One count of usable cores for the services and the benches: affinity, not the host's count."""

from __future__ import annotations

import os

from scmr_mesh import _cpu
from scmr_mesh.bench import usable_cores as bench_usable_cores
from scmr_mesh.mesh.data_service import DATA_PROCESS_MIN_CORES, data_process_wanted
from scmr_mesh.mesh.server import Service
from scmr_mesh.mesh.testing import STUB


def test_usable_cores_is_the_affinity_and_the_benches_use_the_same_function(monkeypatch):
    assert bench_usable_cores is _cpu.usable_cores
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 5, 7})
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert _cpu.usable_cores() == 3


def test_without_affinity_the_host_s_count_is_used(monkeypatch):
    def no_affinity(pid):
        raise OSError("not supported")

    monkeypatch.setattr(os, "sched_getaffinity", no_affinity)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert _cpu.usable_cores() == 1
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert _cpu.usable_cores() == 6


def test_data_process_auto_follows_the_usable_cores_and_on_off_win(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 64)  # a big host, pinned below
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(DATA_PROCESS_MIN_CORES - 1)))
    assert data_process_wanted("auto") is False
    assert data_process_wanted("on") is True
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(DATA_PROCESS_MIN_CORES)))
    assert data_process_wanted("auto") is True
    assert data_process_wanted("off") is False


def test_a_service_s_default_workers_are_the_usable_cores(monkeypatch):
    monkeypatch.setattr(_cpu, "usable_cores", lambda: 3)
    svc = Service("cloudx", tier="cloud", process=STUB)
    try:
        assert len(svc.worker_pids) == 3
    finally:
        svc.shutdown()
