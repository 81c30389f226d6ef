"""Leadership role changes as structured events: what the election writes and the reports read (pure).

A candidate (:class:`scmr_mesh.mesh.election.Candidate`) appends one JSON line
per role change to ``RUN/leadership/<node>.jsonl``; :mod:`scmr_mesh.qos.leadership`
builds the report's ``leadership`` block from them.  The report reads the
typed fields (``event``, ``why``, ``by``), never the human-readable ``cause``
text, so rewording a log line cannot change a report.

>>> c = RoleChange(5, "L", RoleEvent.STEP_DOWN, 2, Why.OUTRANKED, by="r3", cause="outranked by r3 (term 2 vs 1)")
>>> RoleChange.from_json(c.to_json()) == c
True
>>> c.to_json()["why"], c.to_json()["by"]
('outranked', 'r3')
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

__all__ = ["RoleChange", "RoleEvent", "Why"]


class RoleEvent(str, Enum):
    """A candidate took the lead or gave it up."""

    LEAD = "lead"
    STEP_DOWN = "step_down"

    def __str__(self) -> str:
        return self.value


class Why(str, Enum):
    """Why the role changed (the election's decision, or the process stopping)."""

    VACANCY = "vacancy"        # claimed: no live leader, this node's turn
    OUTRANKED = "outranked"    # stepped down: a better leader (``by``) was seen, directly or via another candidate
    STOPPING = "stopping"      # stepped down: the process is stopping
    FAILED = "failed"          # stepped down: serving as leader could not be kept up
    OTHER = "other"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class RoleChange:
    """One role change of one candidate (a JSON line of ``RUN/leadership/<node>.jsonl``)."""

    t_unix_ns: int
    node: str
    event: RoleEvent
    term: int
    why: Why = Why.OTHER
    by: str | None = None
    cause: str = ""  # for people only: nothing parses it
    leaders_seen: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"t_unix_ns": self.t_unix_ns, "node": self.node, "event": self.event.value, "term": self.term,
                "why": self.why.value, "by": self.by, "cause": self.cause, "leaders_seen": list(self.leaders_seen)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RoleChange | None:
        """The change a JSON line holds, or None when it is not one (a line of another format, damaged)."""
        try:
            return cls(t_unix_ns=int(d["t_unix_ns"]), node=str(d["node"]), event=RoleEvent(d["event"]),
                       term=int(d.get("term", 0)), why=Why(d.get("why", "other")),
                       by=None if d.get("by") is None else str(d["by"]), cause=str(d.get("cause", "")),
                       leaders_seen=tuple(d.get("leaders_seen") or ()))
        except (KeyError, TypeError, ValueError):
            return None
