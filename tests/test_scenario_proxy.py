"""The proxy backend's LinkProxy, driven with plain sockets (no root, no zenoh). ~3 s."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from scmr_mesh.errors import ScenarioError
from scmr_mesh.scenario.plan import Event
from scmr_mesh.scenario.proxy import LinkProxy, ProxyBackend
from scmr_mesh.scenario.spec import parse_scenario


@pytest.fixture
def echo():
    """An echo server on 127.0.0.1; yields its port."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    stop = threading.Event()

    def serve(c):
        with c:
            while True:
                try:
                    d = c.recv(65536)
                except OSError:
                    return
                if not d:
                    return
                c.sendall(d)

    def loop():
        srv.settimeout(0.1)
        while not stop.is_set():
            try:
                c, _ = srv.accept()
            except OSError:
                continue
            threading.Thread(target=serve, args=(c,), daemon=True).start()

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    yield srv.getsockname()[1]
    stop.set()
    t.join()
    srv.close()


@pytest.fixture
def proxy(echo):
    px = LinkProxy(("127.0.0.1", echo), name="t")
    px.start()
    yield px
    px.close()


def _client(px):
    c = socket.create_connection(("127.0.0.1", px.port), timeout=5)
    return c


def _recv_exact(c, n):
    buf = b""
    while len(buf) < n:
        d = c.recv(n - len(buf))
        if not d:
            break
        buf += d
    return buf


def test_forwards_both_ways(proxy):
    with _client(proxy) as c:
        c.sendall(b"hello")
        assert _recv_exact(c, 5) == b"hello"
    assert proxy.endpoint == f"tcp/127.0.0.1:{proxy.port}"


def test_blackhole_is_silent_and_holds_bytes_until_the_link_returns(proxy):
    with _client(proxy) as c:
        c.sendall(b"a")
        assert _recv_exact(c, 1) == b"a"
        proxy.set_mode("blackhole")
        c.sendall(b"held")  # no error: the socket stays open, nothing comes back
        c.settimeout(0.4)
        with pytest.raises(socket.timeout):
            c.recv(10)
        proxy.set_mode("forward")
        c.settimeout(5)
        assert _recv_exact(c, 4) == b"held"  # delayed, not lost (TCP semantics)


def test_down_closes_connections_and_refuses_new_ones(proxy):
    c = _client(proxy)
    c.sendall(b"x")
    assert _recv_exact(c, 1) == b"x"
    proxy.set_mode("down")
    c.settimeout(5)
    try:
        got = c.recv(10)
    except ConnectionResetError:
        got = b""
    assert got == b""  # closed (FIN or RST), unlike blackhole
    c.close()
    c2 = _client(proxy)
    c2.settimeout(5)
    try:
        assert c2.recv(10) == b""
    except ConnectionResetError:
        pass
    c2.close()
    assert proxy.connections == 0


def test_rate_limit_is_respected(proxy):
    rate = 200_000.0  # bytes/s per direction
    proxy.set_rate(rate)
    payload = b"z" * 60_000
    with _client(proxy) as c:
        t0 = time.monotonic()
        threading.Thread(target=c.sendall, args=(payload,), daemon=True).start()
        got = _recv_exact(c, len(payload))
        elapsed = time.monotonic() - t0
    assert got == payload
    # the proxy never moves more than rate * elapsed (plus one 10 ms slice) in a direction
    assert len(payload) <= rate * elapsed + rate * 0.01 + 1


def test_delay_applies_each_way(proxy):
    proxy.set_delay(0.1)
    with _client(proxy) as c:
        t0 = time.monotonic()
        c.sendall(b"ping")
        assert _recv_exact(c, 4) == b"ping"
        assert time.monotonic() - t0 >= 0.2  # one-way delay, both directions


def test_bad_mode_is_an_error(proxy):
    with pytest.raises(ScenarioError, match="got 'sideways'"):
        proxy.set_mode("sideways")


def test_backend_wires_links_through_proxies_and_applies_events():
    sc = parse_scenario({"name": "p", "seed": 0, "duration_s": 5,
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"}]},
                         "faults": [{"kind": "link_down", "at_s": 1, "for_s": 1, "link": ["robot1", "cloud"]}]})
    be = ProxyBackend(sc)
    be.setup()
    try:
        assert len(be.proxies) == len(sc.links) == 3  # link faults: every pair through its own proxy
        # robot1 connects only to proxies, never to the servers' own ports
        eps = be.connect("robot1")
        assert len(eps) == 2 and not set(eps) & {be.listen("cloud")[0], be.listen("leader")[0]}
        assert be.extra_cfg("robot1") == ["scouting/gossip/enabled:false"]
        be.apply(Event(1.0, "block", ("cloud", "robot1"), fault=0))
        assert be.proxies[("robot1", "cloud")].mode == "blackhole"
        assert be.proxies[("robot1", "leader")].mode == "forward"
        be.apply(Event(2.0, "unblock", ("cloud", "robot1"), fault=0, lift=True))
        assert be.proxies[("robot1", "cloud")].mode == "forward"
    finally:
        be.teardown()


def test_backend_without_link_faults_hands_each_peer_its_bootstrap_and_keeps_gossip():
    sc = parse_scenario({"name": "p", "seed": 0, "duration_s": 5,
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"},
                                              {"id": "robot2", "synthetic": "stub", "bootstrap": "robot1"}]},
                         "faults": [{"kind": "crash", "at_s": 1, "peer": "cloud"}]})
    be = ProxyBackend(sc)
    be.setup()
    try:
        assert be.proxies == {} and be.extra_cfg("robot2") == []
        # robot2 names its bootstrap: only that; robot1 also dials the leader (re-dialled after a cut)
        assert be.connect("robot2") == be.listen("robot1")
        assert be.connect("robot1") == be.listen("cloud") + be.listen("leader")
        assert be.connect_names("robot2") == ["robot1"]
    finally:
        be.teardown()


def test_cli_run_with_proxy_backend_reports_and_exits_1_on_a_failed_expectation(tmp_path):
    """Real peers (stub pipeline) behind proxies; an expectation that the fault breaks makes exit status 1. ~12 s."""
    import json
    import subprocess
    import sys

    sc = tmp_path / "drop.toml"
    sc.write_text("""
name = "proxy-drop"
seed = 5
duration_s = 6
lease_ms = 200
process = "scmr_mesh.mesh.testing:stub_process"
[fleet]
robots = [ { id = "robot1", synthetic = "stub", rate_hz = 8, local_fallback = false } ]
[[faults]]
kind = "link_down"
at_s = 2.5
for_s = 2.0
link = ["robot1", "cloud"]
[[expectations]]
metric = "leader_answers"
op = "=="
value = 0
""")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "scenario", "run", str(sc), "--backend", "proxy",
                        "--out", str(out), "--json", str(tmp_path / "r.json")],
                       capture_output=True, text=True, timeout=180)
    assert "Traceback" not in r.stderr
    assert "scenario: robots ready" in r.stderr and "blackhole" not in r.stdout
    rep = json.loads((tmp_path / "r.json").read_text())
    assert r.returncode == 1, r.stdout + r.stderr  # leader_answers == 0 cannot hold: the link went down
    assert rep["expectations"] == [{"name": "leader_answers == 0", "metric": "leader_answers",
                                    "observed": rep["summary"]["by_tier"]["leader"], "held": False},
                                   {"name": "telemetry_lost <= 0", "metric": "telemetry_lost",  # the default
                                    "observed": rep["telemetry"]["lost"], "held": rep["telemetry"]["lost"] == 0}]
    assert "  telemetry: " in r.stdout and "expectation telemetry_lost <= 0" in r.stdout
    assert rep["summary"]["by_tier"]["leader"] > 0 and rep["seed"] == 5
    f = rep["faults"][0]
    assert f["kind"] == "link_down" and f["at_s"] == 2.5 and f["failover_gap_ms"] is not None
    assert {"requests", "succeeded", "ror", "tor_ms", "by_tier"} <= set(rep["summary"])
    assert {"p50", "p99"} <= set(rep["summary"]["tor_ms"])
    row = rep["request_log"][0]  # one report for every run: "requests" is the count (report.schema.json)
    assert {"robot", "image", "bytes_up", "bytes_down", "sent_unix_ns", "received_unix_ns", "tor_ms",
            "served_by", "tier"} <= set(row)
    for name in ("report.md", "tor.png", "tiers.png"):
        assert (out / name).stat().st_size > 0


def test_crash_and_restart_through_the_runner(tmp_path):
    """SIGKILL the cloud, restart it: the leader answers meanwhile, the cloud again after. ~12 s (3 s after the restart to fail back)."""
    from scmr_mesh.scenario.report import build_report
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "crash", "seed": 2, "duration_s": 6, "lease_ms": 200,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "rate_hz": 8, "local_fallback": False}]},
        "faults": [{"kind": "crash", "at_s": 2.0, "for_s": 1.0, "peer": "cloud"}],
    })
    res = run_scenario(sc, backend="proxy", out_dir=tmp_path, ready_timeout=90)
    af = res.faults[0]
    assert af.start_unix_ns is not None and af.end_unix_ns is not None and af.restarted == "cloud-2"
    assert (tmp_path / "logs" / "cloud-2.log").is_file()
    rep = build_report(sc, res.records, res.metric_faults(), t0_unix_ns=res.t0_unix_ns, backend="proxy")
    f = rep["faults"][0]
    assert f["tier"] == "cloud" and f["failover_gap_ms"] is not None
    leader = [r for r in res.records if r["ok"] and r["tier"] == "leader"]
    # before the crash the leader answers only hedges: a cloud slow to send its receipt or answer
    # (a loaded box: under stress-ng --cpu 2 one was, in 1 of 3 suite runs) is hedged to it
    assert leader and all(r["received_unix_ns"] >= af.start_unix_ns or r["hedge_won"] for r in leader), \
        [(r["seq"], r["attempts"]) for r in leader if r["received_unix_ns"] < af.start_unix_ns]
    if af.ready_unix_ns is not None and af.ready_unix_ns < res.records[-1]["sent_unix_ns"]:
        # the restarted cloud served again
        assert f["failback_gap_ms"] is not None and f["restart_ready_after_ms"] > 0


def test_an_output_folder_holding_a_run_is_refused_before_anything_starts(tmp_path):
    """Peers append to robots/*/records.jsonl and leadership/*.jsonl: a second run into the same
    folder mixed an old run's leadership events into the new report (two leaders at the end)."""
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({"name": "again", "seed": 1, "duration_s": 1, "process": "scmr_mesh.mesh.testing:stub_process",
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"}]}})
    (tmp_path / "leadership").mkdir()
    (tmp_path / "leadership" / "leader.jsonl").write_text('{"event": "lead"}\n')
    with pytest.raises(ScenarioError, match=r"already holds a scenario run \(leadership/ not empty\); give a new --out"):
        run_scenario(sc, backend="proxy", out_dir=tmp_path)
    assert not (tmp_path / "certs").exists()  # refused before any set-up


def test_bench_scenario_refuses_a_used_run_folder_before_the_first_run(tmp_path, capsys):
    from pathlib import Path

    from scmr_mesh.cli import main

    (tmp_path / "run2" / "robots" / "robot1").mkdir(parents=True)
    (tmp_path / "run2" / "robots" / "robot1" / "records.jsonl").write_text("{}\n")
    scen = Path(__file__).resolve().parents[1] / "peers" / "scenarios" / "baseline.toml"
    assert main(["bench", "scenario", str(scen), "--runs", "3", "--backend", "proxy", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 'run2'} already holds a scenario run" in err and "give a new --out" in err
    assert not (tmp_path / "run1").exists()  # nothing ran
