"""Live energy-aware placement for a robot peer (pure: no Zenoh).

:class:`EnergyPlacer` plugs into the robot of :mod:`scmr_mesh.mesh.robot`:

* as ``Robot.placement`` (``placer(view, frame) -> tiers to try, in order``):
  it builds a :class:`~scmr_mesh.energy.placement.Task` from what it has
  measured so far and calls :func:`~scmr_mesh.energy.placement.choose_placement`
  over the tiers alive in ``view``;
* as a record annotator (``placer.annotate(record, reply)``, called before the
  record is written): it learns from the finished request and adds
  ``energy_j`` (robot energy of what actually happened, J) and ``energy``
  (details, with each input marked measured or assumed) to the record.

Measured inputs (assumed until the first measurement):

* ``C``: cycles = CPU time of a local pipeline run (``reply["cpu_ms"]``) or the
  server's pipeline wall time (sum of ``reply["timings_ms"]``; same-host
  assumption) x this host's clock (:func:`~scmr_mesh.energy.measure.host_clock_hz`).
  Assumed: the thesis's 5e9 cycles.
* ``D_up``: the frame's encoded size (measured per frame); ``D_down``: the
  smoothed size of past replies (assumed 4096 B before the first).
* ``B``: per tier, from the successful attempt's send-to-reply time minus the
  server time (:class:`~scmr_mesh.energy.measure.LinkEstimator`).  Assumed:
  the thesis's 23/28 Mb/s.

Exploration: when the policy keeps choosing local, a reachable tier whose link
has fewer than ``probe_until`` (3) observations is tried once every
``probe_every`` (10) decisions so its rate gets measured (``energy.probe`` is
true on those records).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from typing import Any

from scmr_mesh.energy.measure import EnergyLedger, LinkEstimator, host_clock_hz
from scmr_mesh.energy.model import THESIS_CYCLES, THESIS_F, Profile, e_proc, e_trans
from scmr_mesh.energy.placement import (
    REMOTE_TIERS,
    LinkEstimate,
    Placement,
    Task,
    choose_placement,
    energy_terms,
)

__all__ = ["ASSUMED_LINK", "EnergyPlacer"]

log = logging.getLogger(__name__)

#: Link assumed before any transfer is observed: thesis Eq 4.9 (23 / 28 Mb/s).
ASSUMED_LINK = LinkEstimate(3014656.0, 3670016.0)


class EnergyPlacer:
    """Energy-aware placement hook and per-request energy recorder for one robot.

    Parameters
    ----------
    profile : Profile
        The robot's power profile.
    robot_id : str
        For the ledger.
    deadline_s : float, optional
        Task deadline ``T`` (the robot's per-request deadline is a good choice).
    dvs : bool
        DVS for local execution (Eq 3.16-3.17).
    cloud_factor : float
        ``F`` (cloud clock = ``F * S_r``).
    assumed_link : LinkEstimate
        Link used for a tier until its rate is measured.
    assumed_cycles : float
        ``C`` until measured.
    assumed_reply_bytes : int
        ``D_down`` until measured.
    host_hz : float, optional
        This host's clock; default :func:`host_clock_hz`.
    probe_every : int
        Every N decisions that chose local, try a reachable tier with fewer
        than ``probe_until`` link observations instead (0: never).
    probe_until : int
        Observations per tier after which probing stops (the first transfer
        includes connection warm-up, so one is not enough).
    alpha : float
        EWMA weight for cycles, reply size and link rates.
    """

    def __init__(
        self,
        profile: Profile,
        *,
        robot_id: str = "",
        deadline_s: float | None = None,
        dvs: bool = False,
        cloud_factor: float = THESIS_F,
        assumed_link: LinkEstimate = ASSUMED_LINK,
        assumed_cycles: float = THESIS_CYCLES,
        assumed_reply_bytes: int = 4096,
        host_hz: float | None = None,
        probe_every: int = 10,
        probe_until: int = 3,
        alpha: float = 0.3,
    ) -> None:
        self.profile = profile
        self.deadline_s = deadline_s
        self.dvs = dvs
        self.cloud_factor = cloud_factor
        self.assumed_link = assumed_link
        self.assumed_cycles = float(assumed_cycles)
        self.assumed_reply_bytes = int(assumed_reply_bytes)
        if host_hz is None:
            self.host_hz, self.host_hz_source = host_clock_hz()
        else:
            self.host_hz, self.host_hz_source = float(host_hz), "given"
        self.probe_every = int(probe_every)
        self.probe_until = int(probe_until)
        self.alpha = alpha
        self.links = LinkEstimator(alpha=alpha)
        self.ledger = EnergyLedger(robot_id, profile.name)
        self._cycles: float | None = None
        self._reply: float | None = None
        self._pending: dict[int, tuple[Placement, bool]] = {}
        self._decisions = 0
        self._lock = threading.Lock()

    # ------------------------------------------------------------ inputs
    def task_for(self, nbytes: int) -> Task:
        """The task for a frame of ``nbytes`` encoded bytes, from current estimates."""
        measured = {"bytes_up"}
        if self._cycles is not None:
            measured.add("cycles")
        if self._reply is not None:
            measured.add("bytes_down")
        return Task(
            cycles=self._cycles if self._cycles is not None else self.assumed_cycles,
            bytes_up=int(nbytes),
            bytes_down=int(round(self._reply)) if self._reply is not None else self.assumed_reply_bytes,
            deadline_s=self.deadline_s,
            measured=frozenset(measured),
        )

    def _ewma(self, old: float | None, new: float) -> float:
        return new if old is None else self.alpha * new + (1 - self.alpha) * old

    def _link(self, tier: str) -> LinkEstimate:
        return self.links.estimate(tier) or self.assumed_link

    @staticmethod
    def _peer_clock(view: Any) -> float | None:
        """Clock (Hz) of the first peer the view offers (spare capacity first), if it published one."""
        peers = view.nodes("peer") if hasattr(view, "nodes") else ()
        clocks = getattr(view, "clocks", {}) or {}
        return clocks.get(peers[0]) if peers else None

    # ---------------------------------------------------------- the hook
    def __call__(self, view: Any, frame: Any) -> list[str]:
        """``Robot.placement``: the tiers to try for ``frame``, best first.

        ``view`` needs ``nodes(tier)`` and ``local``; ``frame`` needs ``seq``
        and ``bytes``.
        """
        reachable = [t for t in REMOTE_TIERS if view.nodes(t)]
        if "peer" in reachable and "cloud" in reachable:
            reachable.remove("peer")  # robots serve robots only while no cloud is alive (docs/R2R.md)
        with self._lock:
            task = self.task_for(frame.bytes)
            links = {t: self._link(t) for t in REMOTE_TIERS}
            peer_hz = self._peer_clock(view)
            if peer_hz is not None:  # E_saved with the best spare peer's own clock (its load message)
                links["peer"] = dataclasses.replace(links["peer"], remote_hz=peer_hz)
            p = choose_placement(
                task, self.profile, reachable=reachable, links=links, dvs=self.dvs, cloud_factor=self.cloud_factor
            )
            ranked = [p.tier] + [
                o["tier"]
                for o in sorted(p.options, key=lambda o: (not o["meets_deadline"], o["robot_energy_j"]))
                if o["tier"] != p.tier
            ]
            probe = False
            self._decisions += 1
            if p.tier == "local" and self.probe_every > 0 and self._decisions % self.probe_every == 0:
                unmeasured = sorted(
                    (t for t in reachable if self.links.observations(t) < self.probe_until),
                    key=self.links.observations,
                )
                if unmeasured:
                    ranked = [unmeasured[0]] + [t for t in ranked if t != unmeasured[0]]
                    probe = True
            self._pending[int(frame.seq)] = (p, probe)
            if len(self._pending) > 1000:  # records that never came back
                self._pending.pop(next(iter(self._pending)))
        if not getattr(view, "local", True):
            ranked = [t for t in ranked if t != "local"]
        log.debug("seq %s: %s%s", frame.seq, p.reason, " (probe)" if probe else "")
        return ranked

    # ------------------------------------------------------ the annotator
    def annotate(self, record: dict, reply: dict | None) -> None:
        """Learn from a finished request and add ``energy_j`` and ``energy`` to ``record``.

        Parameters
        ----------
        record : dict
            The robot's record (``seq, ok, tier, bytes_up, bytes_down, tor_ms,
            received_unix_ns, attempts``); modified in place.
        reply : dict or None
            The decoded reply (``server_ms``, ``timings_ms``) of a remote tier,
            or the local result (``cpu_ms``), or None.
        """
        with self._lock:
            planned, probe = self._pending.pop(int(record.get("seq", -1)), (None, False))
            tier = record.get("tier")
            ok = bool(record.get("ok"))
            run_cycles = self._learn(record, reply, tier, ok)
            cycles = run_cycles if run_cycles else (self._cycles or self.assumed_cycles)
            energy, how = self._cost(record, tier, ok, cycles, planned)
            record["energy_j"] = energy
            task = self.task_for(int(record.get("bytes_up") or 0))
            record["energy"] = {
                "profile": self.profile.name,
                "tier": tier,
                "how": how,
                "cycles": cycles,
                "cycles_source": "measured (this run)" if run_cycles else (
                    "measured (smoothed)" if self._cycles is not None else "assumed"),
                "planned_tier": planned.tier if planned else None,
                "predicted_j": planned.robot_energy_j if planned else None,
                "deadline_missed": planned.deadline_missed if planned else None,
                "probe": probe,
                "measured": sorted(
                    [f for f in ("cycles", "bytes_down") if f in task.measured]
                    + ["bytes_up"]
                    + [f"{t}.link" for t in REMOTE_TIERS if self.links.observations(t)]
                ),
                "assumed": sorted(
                    [f for f in ("cycles", "bytes_down") if f not in task.measured]
                    + [f"{t}.link" for t in REMOTE_TIERS if not self.links.observations(t)]
                    + ["powers", "robot_clock", "cloud_factor"]
                ),
            }
            if planned is not None:
                self.ledger.record(planned, tier=tier or "failed", energy_j=energy)

    def _learn(self, record: dict, reply: dict | None, tier: str | None, ok: bool) -> float | None:
        """Update cycles, reply size and link estimates; return this run's cycles if measured."""
        if not ok or not reply:
            return None
        run_cycles = None
        if tier == "local":
            cpu_ms = reply.get("cpu_ms")
            if cpu_ms:
                run_cycles = float(cpu_ms) / 1e3 * self.host_hz
        elif tier in REMOTE_TIERS:
            work_ms = sum(float(v) for v in (reply.get("timings_ms") or {}).values())
            if work_ms > 0:
                run_cycles = work_ms / 1e3 * self.host_hz
            self._reply = self._ewma(self._reply, float(record.get("bytes_down") or 0))
            elapsed = self._elapsed_of_success(record)
            if elapsed and elapsed > 0:
                # bytes_up counts every send; the successful one carried one payload
                sends = [a for a in record.get("attempts", [])
                         if a.get("tier") in REMOTE_TIERS and a.get("outcome") != "unreachable"]
                nbytes_up = int(record.get("bytes_up") or 0) // max(1, len(sends))
                self.links.observe(
                    tier,
                    bytes_up=nbytes_up,
                    bytes_down=int(record.get("bytes_down") or 0),
                    elapsed_s=elapsed,
                    server_s=min(float(reply.get("server_ms") or 0.0) / 1e3, elapsed),
                )
        if run_cycles:
            self._cycles = self._ewma(self._cycles, run_cycles)
        return run_cycles

    @staticmethod
    def _elapsed_of_success(record: dict) -> float | None:
        recv = record.get("received_unix_ns")
        for a in record.get("attempts", []):
            if a.get("outcome") == "ok" and recv and a.get("t_unix_ns"):
                return (int(recv) - int(a["t_unix_ns"])) / 1e9
        tor = record.get("tor_ms")
        return float(tor) / 1e3 if tor else None

    def _cost(
        self, record: dict, tier: str | None, ok: bool, cycles: float, planned: Placement | None
    ) -> tuple[float, str]:
        """Robot energy of what happened, J, and how it was costed."""
        prof = self.profile
        up = int(record.get("bytes_up") or 0)
        down = int(record.get("bytes_down") or 0)
        if ok and tier == "local":
            local = planned.options[0] if planned is not None else None
            if local is not None and local.get("dvs"):
                f = local["clock_hz"]
                return cycles * prof.dvs_k * f * f, "Eq 3.16 k*f^2 per cycle at the DVS clock"
            return e_proc(cycles, p_compute_w=prof.p_compute_w, clock_hz=prof.clock_hz), "Eq 4.2 P_c*C/S_r"
        if ok and tier in REMOTE_TIERS:
            terms = energy_terms(Task(cycles, up, down), prof, self._link(tier), tier=tier, cloud_factor=self.cloud_factor)
            return terms["e_cloud_j"], "Eq 4.3-4.4 P_i*C/S_c + P_u*D_up/B_u + P_d*D_down/B_d"
        # failed: the robot still sent bytes_up and waited tor_ms
        link = self.assumed_link
        wait_s = float(record.get("tor_ms") or 0.0) / 1e3
        sent = e_trans(up, 0, p_up_w=prof.p_up_w, p_down_w=prof.p_down_w, up_Bps=link.up_Bps, down_Bps=link.down_Bps)
        return sent + prof.p_idle_w * wait_s, "failed: P_u*D_up/B_u + P_i*ToR"

    def summary(self) -> dict[str, Any]:
        """Ledger summary plus the current estimates (for the robot's final JSON line)."""
        s = self.ledger.summary()
        s["estimates"] = {
            "cycles": self._cycles,
            "cycles_source": "measured" if self._cycles is not None else "assumed",
            "host_hz": self.host_hz,
            "host_hz_source": self.host_hz_source,
            "reply_bytes": self._reply,
            "links_Bps": {t: (self.links.estimate(t).up_Bps if self.links.estimate(t) else None) for t in REMOTE_TIERS},
        }
        return s
