"""Faults as a run applies them: which tier each takes away, when it took effect, what the engine emits.

:class:`AppliedFault` is the runner's mutable note of one fault while the run
goes on; :func:`fault_records` turns the notes into the frozen
:class:`~scmr_mesh.qos.faults.FaultRecord` s that metrics, leadership and
reports read (:func:`metric_faults`: their JSON form).  Pure: nothing here
starts a process.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from scmr_mesh.qos.faults import FaultRecord
from scmr_mesh.scenario.plan import affected_pairs
from scmr_mesh.scenario.spec import WHOEVER_LEADS, Fault, Scenario

__all__ = ["AppliedFault", "fault_records", "fault_tier", "metric_faults"]


def fault_tier(scenario: Scenario, fault: Fault) -> tuple[str | None, list[str] | None]:
    """Which serving tier ``fault`` takes away, and from which robots (pure).

    Returns ``(tier, robots)`` in the form :mod:`scmr_mesh.qos.metrics` expects:
    ``tier`` is ``"cloud"``, ``"leader"`` or ``None``; ``robots`` ``None``
    means every robot.
    """
    robots = [r.id for r in scenario.robots]
    if fault.kind == "crash":
        crashed = set(fault.crashed)
        if crashed == {WHOEVER_LEADS} or (scenario.leader and scenario.leader in crashed):
            return "leader", None
        if scenario.clouds and set(scenario.clouds) <= crashed:
            return "cloud", None
        return None, None  # a robot, or some of several cloud nodes: the others still serve
    if fault.kind in ("link_down", "partition"):
        pairs = set(affected_pairs(fault))
        for tier, servers in (("cloud", scenario.clouds), ("leader", (scenario.leader,) if scenario.leader else ())):
            if not servers:
                continue
            cut = [r for r in robots if all(tuple(sorted((r, s))) in pairs for s in servers)]
            if cut:
                return tier, (None if len(cut) == len(robots) else cut)
    return None, None


@dataclass
class AppliedFault:
    """When one fault really took effect (unix ns) and what was skipped."""

    index: int
    fault: Fault
    start_unix_ns: int | None = None
    end_unix_ns: int | None = None
    restarted: str | None = None  # supervisor name of the (first) restarted process (crash faults)
    ready_unix_ns: int | None = None  # when the (first) restarted peer wrote its ready file
    notes: list[str] = field(default_factory=list)
    killed: list[str] = field(default_factory=list)  # supervisor names this crash SIGKILLed
    restarted_all: list[str] = field(default_factory=list)  # every restarted process (a cloud tier: each node)
    resolved: str | None = None  # the peer a crash of whoever leads hit


def fault_records(scenario: Scenario, applied: Sequence[AppliedFault], t0_unix_ns: int) -> list[FaultRecord]:
    """The faults as they took effect: the :class:`~scmr_mesh.qos.faults.FaultRecord` s the engine emits (pure).

    ``target`` names nodes (``cloud0``; a link ``robot1-cloud``; a partition's
    groups); a crash of whoever leads names the node it hit and, in ``peer``,
    its process; ``killed`` and ``restarted`` the processes a crash stopped and
    started again.
    """
    out = []
    for af in applied:
        f = af.fault
        tier, robots = fault_tier(scenario, f)
        crashed = [af.resolved or p for p in f.crashed]
        target = (",".join(scenario.node_of(p) for p in crashed) if crashed else
                  "-".join(f.link) if f.link else " | ".join(",".join(g) for g in f.groups or ()))
        out.append(FaultRecord(
            kind=f.kind, target=target, label=f.label, tier=tier, link=f.link, robots=robots, groups=f.groups,
            at_s=f.at_s, for_s=f.for_s, fallback=("peer", "leader") if tier == "leader" else None,
            peer=(af.killed[0] if af.killed else str(af.resolved)) if af.resolved else None,
            start_unix_ns=af.start_unix_ns if af.start_unix_ns is not None else t0_unix_ns + int(f.at_s * 1e9),
            end_unix_ns=af.end_unix_ns, ready_unix_ns=af.ready_unix_ns, notes=tuple(af.notes),
            killed=tuple(af.killed), restarted=tuple(af.restarted_all)))
    return out


def metric_faults(scenario: Scenario, applied: Sequence[AppliedFault], t0_unix_ns: int) -> list[dict[str, Any]]:
    """:func:`fault_records` in their JSON form (``report.json``'s ``faults``, ``run.json``)."""
    return [f.as_dict() for f in fault_records(scenario, applied, t0_unix_ns)]
