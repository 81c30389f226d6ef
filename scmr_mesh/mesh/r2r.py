"""A leader-capable node of the R2R tier: one warm service in two roles.

:class:`R2RNode` ties together, on one Zenoh session:

* a :class:`~scmr_mesh.mesh.server.Service` whose worker pool was forked and
  warmed at start.  While another node leads, it serves other robots on the
  peer tier (``scmr/drivable/peer/<node>``, token ``scmr/alive/peer/<node>``,
  load with the node's clock on ``scmr/load/peer/<node>``); when this node is
  elected it serves as the leader (``scmr/drivable/leader/<node>``, token
  ``scmr/alive/leader/<node>``) with the leader's data queryables;
* a :class:`~scmr_mesh.mesh.data_service.LeaderData`: its data-buffer copy is
  pulled from the leader while standing by (anti-entropy) and from the clouds
  while leading, so a successor serves buffer reads at most one sync period
  old; its relay queue holds what robots sent while it led;
* a :class:`~scmr_mesh.mesh.election.Candidate`, which decides when to switch.

Switching roles undeclares the old queryable and token and declares the new
ones without draining: requests admitted under the old role are still
answered by the pool (the reply names the tier they arrived on).

The node owns its declarations: ``with R2RNode(...) as node: node.attach(session)``
gives up the lead, the candidacy, the served queryable and token and the data
copy on leaving the block (:meth:`R2RNode.close`).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Callable

from scmr_mesh.mesh.election import Candidate, Capability
from scmr_mesh.vocab import Tier

log = logging.getLogger(__name__)


class R2RNode:
    """A candidate for the lead that serves peers while it does not lead.

    Parameters
    ----------
    service : scmr_mesh.mesh.server.Service
        Created (pool forked and warm) before the Zenoh session was opened.
    data : LeaderData or None
        The node's data tier (None when the data tier is off).
    capability : Capability
        Its rank in the election (energy profile).
    serve_peers : bool
        Serve other robots on the peer tier while not leading.
    events_path : path, optional
        Where the candidate appends its role changes (JSON lines).
    election : dict, optional
        Extra keyword arguments of :class:`Candidate` (``grace_s``, ...).
    """

    def __init__(self, service, data, *, capability: Capability, serve_peers: bool = True,
                 events_path: str | Path | None = None, election: dict | None = None) -> None:
        self.svc = service
        self.data = data
        self.serve_peers = serve_peers
        #: what it serves as: ``Tier.LEADER``, ``Tier.PEER``, or "standby" / "stopped"
        self.role: Tier | str = "standby"
        self.session = None
        self._closed = False
        #: ``fn() -> 0..1``: the node's battery (a robot sets its own)
        self.battery: Callable[[], float] = lambda: 1.0
        self._lock = threading.RLock()
        self._warmed = False
        service.capability = (capability.clock_hz, capability.power_w)
        self.candidate = Candidate(
            service.node, capability, on_lead=self._lead, on_step_down=self._step_down,
            battery=lambda: self.battery(), load=self._load, events_path=events_path, **(election or {}))

    @property
    def node(self) -> str:
        return self.svc.node

    def _load(self) -> float:
        st = self.svc.state
        return st.inflight / max(1, st.workers)

    # ------------------------------------------------------- life cycle
    def attach(self, session) -> None:
        """Serve peers (if asked), start the data copy, then run for the lead."""
        self.session = session
        if self.data is not None:
            self.data.leading = False
            self.data.leader_of = self.candidate.leader
            self.data.start(session=session)
        if self.serve_peers:
            self._serve(Tier.PEER)
        self.candidate.attach(session)

    def __enter__(self) -> R2RNode:
        """``with`` owns what the node declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait_settled(self, timeout: float = 5.0) -> bool:
        """Wait until the candidate has passed its start-up grace and decided once."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if time.monotonic() - self.candidate._started >= self.candidate.grace_s:
                self.candidate.evaluate()
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        """Give up the lead and the candidacy, stop serving, stop the data copy (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.candidate.close()
        with self._lock:
            if self.svc.session is not None:
                self.svc.detach()
            self.role = "stopped"
        if self.data is not None:
            self.data.close()

    # ------------------------------------------------------ role changes
    def _serve(self, tier: Tier | None) -> None:
        with self._lock:
            t0 = time.perf_counter()
            if self.svc.session is not None:
                self.svc.detach(drain_s=0.0)
            if tier is None:
                self.role = "standby"
                return
            extra = self.data.queryables() if (tier == Tier.LEADER and self.data is not None) else []
            self.svc.serve_as(tier, extra)
            self.svc.attach(self.session, warm=not self._warmed)
            self._warmed = True
            self.role = tier
            log.info("%s now serves as %s (switch %.1f ms)", self.node, tier, (time.perf_counter() - t0) * 1e3)

    def _lead(self, term: int) -> None:
        try:
            self._serve(Tier.LEADER)
        except Exception:
            # roll back to what it was (the candidate stays a follower): never half-switched
            try:
                self._serve(Tier.PEER if self.serve_peers else None)
            except Exception as exc:
                log.error("%s: could not go back to serving as peer: %s", self.node, exc)
            raise
        if self.data is not None:
            self.data.leading = True

    def _step_down(self, reason: str) -> None:
        if self.data is not None:
            self.data.leading = False
        stopping = self.candidate is not None and self.candidate.closing  # the candidate's close(), not a word
        self._serve(Tier.PEER if self.serve_peers and not stopping else None)


__all__ = ["R2RNode"]
