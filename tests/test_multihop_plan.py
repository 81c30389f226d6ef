"""The routers shape, pure (issue 22): who dials whom, the router and client command lines, identities,
refusals, and the election's "linked" rule for a client of a router.  No root, no processes."""

from __future__ import annotations

from pathlib import Path

import pytest

from scmr_mesh.errors import ConfigError, ScenarioError
from scmr_mesh.scenario.plan import ROUTER_CFG, peer_command, router_command
from scmr_mesh.scenario.spec import parse_scenario

RADIO = {"name": "t", "seed": 1, "duration_s": 5,
         "topology": {"shape": "routers", "range_m": 12,
                      "nodes": {"cloud": [0, 0], "leader": [0, 1], "robot1": [10, 0], "robot2": [20, 0]}},
         "fleet": {"robots": [{"id": "robot1", "synthetic": "tunnel"}, {"id": "robot2", "synthetic": "tunnel"}]}}


def test_every_router_dials_the_hosts_started_before_it_on_a_radio_topology():
    sc = parse_scenario(RADIO)
    assert sc.shape == "routers"
    assert sc.router_dials("cloud") == ()
    assert sc.router_dials("robot2") == ("cloud", "leader", "robot1")  # out of range ones fail in the kernel
    assert sc.router_of("robot2") == "router-robot2"


def test_with_explicit_links_routers_dial_only_their_links():
    sc = parse_scenario({**RADIO, "topology": {"shape": "routers",
                                               "links": [["leader", "cloud"], ["robot1", "leader"],
                                                         ["robot2", "robot1"]]}})
    assert sc.router_dials("robot2") == ("robot1",) and sc.router_dials("robot1") == ("leader",)


def test_the_default_shape_is_the_clique_and_a_bad_shape_is_one_line():
    sc = parse_scenario({**RADIO, "topology": {k: v for k, v in RADIO["topology"].items() if k != "shape"}})
    assert sc.shape == "clique"
    with pytest.raises(ConfigError) as e:
        parse_scenario({**RADIO, "topology": {**RADIO["topology"], "shape": "mesh"}})
    assert "shape" in str(e.value) and "\n" not in str(e.value)


def test_router_and_client_command_lines():
    sc = parse_scenario(RADIO)
    r = router_command(sc, "robot2", run_dir=Path("run"), listen=["tcp/198.18.0.13:7448"],
                       connect=["tcp/198.18.0.10:7448", "tcp/198.18.0.12:7448"], security=["--insecure"])
    argv = list(r.argv)
    assert argv[3:6] == ["router", "--node", "router-robot2"]
    assert argv.count("--connect") == 2 and "--listen" in argv
    for c in ROUTER_CFG:  # gossip off: a router links only what it is handed
        assert argv[argv.index(c) - 1] == "--cfg"
    assert r.ready_file == Path("run/ready/router-robot2.ready")
    assert router_command(sc, "robot2", run_dir=Path("run"), listen=[], connect=[], start=2).name == "router-robot2-2"
    c = peer_command(sc, "robot2", run_dir=Path("run"), connect=["tcp/198.18.0.13:7448"], zmode="client")
    assert c.argv[c.argv.index("--zmode") + 1] == "client" and "--listen" not in c.argv


def test_routers_are_fleet_identities_of_role_router():
    from scmr_mesh.scenario.loopback import LoopbackBackend
    from scmr_mesh.scenario.netns import NetnsBackend
    from scmr_mesh.scenario.runner import router_hosts, scenario_identities

    sc = parse_scenario(RADIO)
    nb = NetnsBackend(sc, run_id="ab12", run=lambda argv: "")
    assert list(router_hosts(sc, nb)) == ["router-cloud", "router-leader", "router-robot1", "router-robot2"]
    assert nb.router_endpoint("robot2") == "tcp/198.18.0.13:7448"
    ids = {p.name: p.role for p in scenario_identities(sc, list(router_hosts(sc, nb)))}
    assert ids["router-robot1"] == "router" and ids["robot1"] == "robot"
    flat = parse_scenario({k: v for k, v in RADIO.items() if k != "topology"} | {"topology": {"shape": "routers"}})
    lb = LoopbackBackend(flat)  # one host: one router, every peer its client
    assert router_hosts(flat, lb) == {"router-localhost": "cloud"}
    assert len({lb.router_endpoint(p) for p in flat.peer_names}) == 1


def test_the_proxy_backend_refuses_the_routers_shape_with_one_line():
    from scmr_mesh.scenario.runner import _make_backend

    with pytest.raises(ScenarioError) as e:
        _make_backend(parse_scenario(RADIO), "proxy")
    assert "routers" in str(e.value) and "netns" in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------ the election's "linked" for a client
class _Decl:
    def undeclare(self):
        pass


class _ClientSession:
    """A client of a router: linked to its router only; the test plays the tokens that reach it."""

    def __init__(self):
        self.any_token = None
        outer = self

        class _Live:
            def declare_subscriber(self, key, cb, history=False):
                if key.endswith("/**"):
                    outer.any_token = cb
                return _Decl()

            def declare_token(self, key):
                return _Decl()

        class _Info:
            def peers_zid(self):
                return iter([])

            def routers_zid(self):
                return iter(["router"])

        self._live, self.info = _Live(), _Info()

    def liveliness(self):
        return self._live

    def declare_subscriber(self, key, cb):
        return _Decl()

    def declare_queryable(self, key, cb):
        return _Decl()

    def declare_publisher(self, key):
        class _P(_Decl):
            def put(self, *a, **k):
                pass
        return _P()

    def get(self, key, timeout=None):
        return []


class _Sample:
    def __init__(self, key, put=True):
        import zenoh

        self.key_expr = key
        self.kind = zenoh.SampleKind.PUT if put else zenoh.SampleKind.DELETE


def test_a_client_is_linked_only_when_another_nodes_token_reaches_it():
    from scmr_mesh.mesh.election import Candidate, Capability

    s = _ClientSession()
    c = Candidate("robot3", Capability(2.5e9, 93.0, "robot4"), on_lead=lambda t: None, on_step_down=lambda r: None)
    c._session = s
    c.attach(s)
    try:
        assert not c._is_linked()  # its own router only: alone, it must not claim
        s.any_token(_Sample("scmr/alive/robot/robot3"))  # its own token says nothing
        assert not c._is_linked()
        s.any_token(_Sample("scmr/alive/robot/robot4"))  # a neighbour's token came over the routers
        assert c._is_linked()
        s.any_token(_Sample("scmr/alive/robot/robot4", put=False))
        assert not c._is_linked()
    finally:
        c.close()


def test_scenario_plan_shows_each_hosts_router_and_refuses_a_proxy_plan(capsys):
    from scmr_mesh.cli import main

    assert main(["scenario", "plan", "peers/scenarios/relay-loss.toml", "--backend", "netns"]) == 0
    out = capsys.readouterr().out
    assert "router router-robot3 on tcp/198.18.0.14:7448 dials cloud, leader, robot1, robot2; robot3 is its client" in out
    assert main(["scenario", "plan", "peers/scenarios/relay-loss.toml", "--backend", "proxy"]) == 1
    err = capsys.readouterr().err
    assert 'shape = "routers" has no proxy plan' in err and err.count("\n") == 1
