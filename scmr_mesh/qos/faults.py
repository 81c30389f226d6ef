"""The one fault vocabulary: what a run's engine emits and metrics, leadership and reports read.

A :class:`FaultRecord` is one fault as it took effect: what it hit, when (unix
ns), which serving tier it took away from which robots, and what the engine
did (processes killed and restarted, notes).  It is frozen, and it reads like
the read-only mapping the report's JSON holds (``f["start_unix_ns"]``,
``f.get("tier")``, ``dict(f)``), so the metrics and the report builder take it
as they take a fault read back from a ``report.json``.

Pure: no Zenoh, no processes.

>>> f = FaultRecord("crash", "cloud0", start_unix_ns=5, tier=Tier.CLOUD, label="crash cloud @1s")
>>> f["tier"], f.get("end_unix_ns"), "killed" in f
('cloud', None, False)
>>> FaultRecord.from_mapping(dict(f)) == f
True
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, fields
from typing import Any

from scmr_mesh.vocab import Tier

__all__ = ["FaultRecord"]

#: Optional fields left out of the mapping when empty (a report's fault has only what applies).
_OMIT_EMPTY = ("fallback", "peer", "killed", "restarted", "groups")


@dataclass(frozen=True)
class FaultRecord(Mapping):
    """One fault as it took effect (see the module docstring).

    ``target`` names nodes (``cloud0``, ``cloud0,cloud1``), a link (``robot1-cloud``)
    or a partition's groups; ``peer`` the process a crash of whoever leads hit;
    ``tier`` the serving tier the fault takes away (None: none, e.g. one of
    several cloud nodes) from ``robots`` (None: all).
    """

    kind: str
    target: str
    start_unix_ns: int
    end_unix_ns: int | None = None
    ready_unix_ns: int | None = None
    tier: Tier | None = None
    robots: tuple[str, ...] | None = None
    label: str = ""
    at_s: float | None = None
    for_s: float | None = None
    link: tuple[str, str] | None = None
    peer: str | None = None
    groups: tuple[tuple[str, ...], ...] | None = None
    fallback: tuple[str, ...] | None = None
    killed: tuple[str, ...] = ()
    restarted: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.tier is not None and not isinstance(self.tier, Tier):
            object.__setattr__(self, "tier", Tier(self.tier))
        for name in ("robots", "link", "fallback", "killed", "restarted", "notes"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, tuple):
                object.__setattr__(self, name, tuple(v))
        if self.groups is not None:
            object.__setattr__(self, "groups", tuple(tuple(g) for g in self.groups))

    # ------------------------------------------------------------ mapping
    def as_dict(self) -> dict[str, Any]:
        """The JSON form (lists, plain strings), as a report holds it."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in _OMIT_EMPTY and not v:
                continue
            if isinstance(v, Tier):
                v = v.value
            elif f.name == "groups":
                v = [list(g) for g in v]
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    def __getitem__(self, key: str) -> Any:
        d = self.as_dict()
        return d[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.as_dict())

    def __len__(self) -> int:
        return len(self.as_dict())

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any]) -> "FaultRecord":
        """Read one back from a report's JSON (unknown keys are ignored)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in m.items() if k in names})
