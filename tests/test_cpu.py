"""One count of usable cores for the services and the benches: affinity and cgroup quota, not the host's count."""

from __future__ import annotations

import os

from scmr_mesh import _cpu
from scmr_mesh.bench import usable_cores as bench_usable_cores
from scmr_mesh.mesh.data_service import DATA_PROCESS_MIN_CORES, data_process_wanted
from scmr_mesh.mesh.server import Service
from scmr_mesh.mesh.testing import STUB


def test_usable_cores_is_the_affinity_and_the_benches_use_the_same_function(monkeypatch):
    assert bench_usable_cores is _cpu.usable_cores
    monkeypatch.setattr(_cpu, "quota_cores", lambda: None)  # the test host's own quota left out
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 5, 7})
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert _cpu.usable_cores() == 3


def test_without_affinity_the_host_s_count_is_used(monkeypatch):
    def no_affinity(pid):
        raise OSError("not supported")

    monkeypatch.setattr(os, "sched_getaffinity", no_affinity)
    monkeypatch.setattr(_cpu, "quota_cores", lambda: None)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert _cpu.usable_cores() == 1
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert _cpu.usable_cores() == 6


def test_data_process_auto_follows_the_usable_cores_and_on_off_win(monkeypatch):
    monkeypatch.setattr(_cpu, "quota_cores", lambda: None)
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


def _files(root, files):
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text + "\n")


def test_a_cgroup_v2_quota_counts_in_whole_cores_the_tightest_ancestor_wins(tmp_path):
    proc = "0::/kubepods/pod1/ctr\n"
    _files(tmp_path, {"cpu.max": "max 100000", "kubepods/cpu.max": "800000 100000",
                      "kubepods/pod1/ctr/cpu.max": "150000 100000"})
    assert _cpu.quota_cores(tmp_path, proc) == 1.5
    _files(tmp_path, {"kubepods/pod1/cpu.max": "100000 100000"})
    assert _cpu.quota_cores(tmp_path, proc) == 1.0
    _files(tmp_path, {"kubepods/pod1/cpu.max": "max 100000", "kubepods/pod1/ctr/cpu.max": "max 100000",
                      "kubepods/cpu.max": "max 100000"})
    assert _cpu.quota_cores(tmp_path, proc) is None


def test_a_cgroup_v1_quota_and_minus_one_for_none(tmp_path):
    proc = "4:memory:/docker/abc\n3:cpu,cpuacct:/docker/abc\n0::/\n"
    _files(tmp_path, {"cpu,cpuacct/cpu.cfs_quota_us": "-1", "cpu,cpuacct/cpu.cfs_period_us": "100000",
                      "cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "200000",
                      "cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000"})
    assert _cpu.quota_cores(tmp_path, proc) == 2.0
    _files(tmp_path, {"cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "-1"})
    assert _cpu.quota_cores(tmp_path, proc) is None
    assert _cpu.quota_cores(tmp_path / "nothing", proc) is None  # no cgroup files at all
    assert _cpu.quota_cores(tmp_path, "garbage\n\n") is None


def test_a_cgroup_v1_cpu_controller_co_mounted_with_others(tmp_path):
    proc = "5:cpuset,cpu,cpuacct:/job\n"
    (tmp_path / "cpu").mkdir()  # an empty folder named like a hierarchy, sorted first: not mounted, passed over
    _files(tmp_path, {"cpuset/cpuset.cpus": "0-63", "cpuset,cpu,cpuacct/cpu.cfs_quota_us": "-1",
                      "cpuset,cpu,cpuacct/cpu.cfs_period_us": "100000",
                      "cpuset,cpu,cpuacct/job/cpu.cfs_quota_us": "400000",
                      "cpuset,cpu,cpuacct/job/cpu.cfs_period_us": "100000"})
    assert _cpu.quota_cores(tmp_path, proc) == 4.0


def test_usable_cores_is_capped_by_the_quota_rounded_down(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(64)))
    monkeypatch.setattr(_cpu, "quota_cores", lambda: 2.5)
    assert _cpu.usable_cores() == 2
    monkeypatch.setattr(_cpu, "quota_cores", lambda: 0.2)
    assert _cpu.usable_cores() == 1
    monkeypatch.setattr(_cpu, "quota_cores", lambda: 3.0)
    assert _cpu.usable_cores() == 3

    def locked(*a):
        raise PermissionError(13, "Permission denied", "/sys/fs/cgroup/cpu")

    monkeypatch.setattr(_cpu, "quota_cores", locked)  # a sandbox that hides the cgroup files
    assert _cpu.usable_cores() == 64
    monkeypatch.setattr(_cpu, "quota_cores", lambda: 128.0)  # a quota above the affinity changes nothing
    assert _cpu.usable_cores() == 64
    monkeypatch.setattr(_cpu, "quota_cores", lambda: None)
    assert _cpu.usable_cores() == 64
