"""The plain backend: every peer on loopback, direct endpoints, no link faults.

What ``scmr up`` and ``scmr demo`` run on: each peer listens on its own
``tcp/127.0.0.1:<port>`` and is handed its bootstrap's endpoint, then those of the
peers started before it (:meth:`~scmr_mesh.scenario.spec.Scenario.dials`: Zenoh re-dials
only these after a cut); gossip scouting links the rest, as on real hosts.  Process faults (crashes and
restarts) are the runner's and work here; a scenario that cuts or shapes links
is refused with one line naming the fault and the backends that can.
"""

from __future__ import annotations

from typing import Sequence

from scmr_mesh.errors import ScenarioError
from scmr_mesh.ports import free_ports
from scmr_mesh.scenario.plan import Event
from scmr_mesh.scenario.spec import Scenario

__all__ = ["LoopbackBackend", "free_ports"]


class LoopbackBackend:
    """Direct loopback endpoints; crash faults only (see the module docstring)."""

    name = "loopback"

    def __init__(self, scenario: Scenario) -> None:
        link = next((f for f in scenario.faults if f.kind != "crash"), None)
        if link is not None:
            raise ScenarioError(
                f"scenario {scenario.name}: the loopback backend cannot cut or shape links "
                f"({link.label}); run it with --backend netns (root) or --backend proxy")
        if scenario.radio is not None:
            raise ScenarioError(
                f"scenario {scenario.name}: the loopback backend cannot apply a radio topology (range_m, nodes); "
                "run it with --backend netns (root) or --backend proxy")
        self.scenario = scenario
        names = list(scenario.peer_names)
        self.ports = free_ports(names + (["router"] if scenario.shape == "routers" else []))
        self.notes: list[str] = []

    def setup(self) -> None:
        pass

    def teardown(self) -> None:
        pass

    def wrap(self, peer: str, argv: Sequence[str]) -> list[str]:
        return list(argv)

    def endpoint(self, peer: str) -> str:
        return f"tcp/127.0.0.1:{self.ports[peer]}"

    def listen(self, peer: str) -> list[str]:
        return [self.endpoint(peer)]

    #: Every peer runs on this one host: under ``shape = "routers"`` they are all clients of one
    #: router (links grow with N, not N^2; rmw_zenoh's one router per host).
    ONE_HOST = "localhost"

    def host_of(self, peer: str) -> str:
        return self.ONE_HOST

    def router_endpoint(self, peer: str) -> str:
        """Where the router of ``peer``'s host (the one router) listens (``shape = "routers"``)."""
        return f"tcp/127.0.0.1:{self.ports['router']}"

    def connect(self, peer: str) -> list[str]:
        return [self.endpoint(b) for b in self.connect_names(peer)]

    def connect_names(self, peer: str) -> list[str]:
        return list(self.scenario.dials(peer))

    def extra_cfg(self, peer: str) -> list[str]:
        return []

    def apply_many(self, events: Sequence[Event]) -> list[str]:
        raise ScenarioError(f"the loopback backend cannot apply {events[0].op} (only crashes and restarts)")
