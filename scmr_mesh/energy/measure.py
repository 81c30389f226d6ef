"""Measured model inputs: cycles from CPU time, link rates from transfers.

* ``C`` (cycles) = the pipeline's measured CPU time on this host x this host's
  clock (x an optional cycles-per-instruction ratio between host and robot;
  1.0 assumes the robot's CPU retires the same work per cycle).  The robot then
  needs ``C / S_r`` seconds at its own clock.
* The host clock comes from ``/proc/cpuinfo`` ("cpu MHz", mean over cores: the
  *current* clock, which may change under frequency scaling), else from
  ``/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq``, else a fallback of
  2.5 GHz marked as assumed.
* Link rates come from observed request/reply transfers (:class:`LinkEstimator`).
* :class:`EnergyLedger` sums per-request robot energy per tier for reports.
"""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable, Mapping

from scmr_mesh.energy.model import _check_positive
from scmr_mesh.energy.placement import REMOTE_TIERS, LinkEstimate, Placement

__all__ = ["FALLBACK_HOST_HZ", "host_clock_hz", "cycles_from_cpu_time", "LinkEstimator", "EnergyLedger"]

log = logging.getLogger(__name__)

#: Host clock assumed when neither /proc/cpuinfo nor cpufreq gives one, Hz.
FALLBACK_HOST_HZ = 2.5e9


def _parse_cpuinfo(text: str) -> float | None:
    mhz = []
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() == "cpu mhz":
            try:
                mhz.append(float(value.strip()))
            except ValueError:
                continue
    mhz = [m for m in mhz if m > 0 and math.isfinite(m)]
    return sum(mhz) / len(mhz) * 1e6 if mhz else None


@lru_cache(maxsize=1)
def host_clock_hz() -> tuple[float, str]:
    """This host's CPU clock and where it came from.

    Returns
    -------
    hz : float
        Clock in Hz.
    source : str
        ``"measured: /proc/cpuinfo cpu MHz"``, ``"measured: cpufreq
        cpuinfo_max_freq"`` or ``"assumed: fallback 2.5 GHz"``.
    """
    try:
        hz = _parse_cpuinfo(Path("/proc/cpuinfo").read_text())
        if hz:
            return hz, "measured: /proc/cpuinfo cpu MHz (mean over cores)"
    except OSError:
        pass
    try:
        khz = float(Path("/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq").read_text().strip())
        if khz > 0:
            return khz * 1e3, "measured: cpufreq cpuinfo_max_freq"
    except (OSError, ValueError):
        pass
    log.warning("host clock unknown; assuming %.2g Hz", FALLBACK_HOST_HZ)
    return FALLBACK_HOST_HZ, "assumed: fallback 2.5 GHz"


def cycles_from_cpu_time(cpu_s: float, host_hz: float | None = None, *, cpi_ratio: float = 1.0) -> float:
    """Task cycles ``C`` from a measured CPU time on this host.

    Parameters
    ----------
    cpu_s : float
        CPU time the task took here, s (e.g. ``time.thread_time()`` around the
        pipeline call).
    host_hz : float, optional
        This host's clock, Hz; default :func:`host_clock_hz`.
    cpi_ratio : float
        Robot cycles per host cycle for the same work (1.0: same IPC; an
        assumption).

    Returns
    -------
    float
        ``cpu_s * host_hz * cpi_ratio`` cycles.

    Examples
    --------
    >>> cycles_from_cpu_time(0.5, 2e9)
    1000000000.0
    """
    _check_positive("cpu_s", cpu_s)
    hz = host_clock_hz()[0] if host_hz is None else _check_positive("host_hz", host_hz)
    _check_positive("cpi_ratio", cpi_ratio)
    return float(cpu_s) * hz * float(cpi_ratio)


class LinkEstimator:
    """Link rate per remote tier from observed request/reply transfers.

    Each observation is one completed remote request: bytes sent and received,
    wall time from send to reply, and the server's own processing time when the
    reply reports it.  The transfer time is ``elapsed - server_s`` and the rate
    ``(bytes_up + bytes_down) / transfer_time`` is applied to both directions
    (a symmetric-link assumption: one request cannot tell them apart).  Rates
    are smoothed with an exponentially weighted moving average.

    Parameters
    ----------
    alpha : float
        EWMA weight of the newest observation, in (0, 1].
    min_transfer_s : float
        Floor on the transfer time, s, so loopback does not give infinite rates.
    """

    def __init__(self, *, alpha: float = 0.3, min_transfer_s: float = 1e-4) -> None:
        if not 0 < alpha <= 1:
            from scmr_mesh.errors import InputError

            raise InputError(f"alpha must be in (0, 1], got {alpha!r}")
        self.alpha = alpha
        self.min_transfer_s = _check_positive("min_transfer_s", min_transfer_s)
        self._rate: dict[str, float] = {}
        self._count: dict[str, int] = defaultdict(int)

    def observe(self, tier: str, *, bytes_up: int, bytes_down: int, elapsed_s: float, server_s: float = 0.0) -> float:
        """Record one transfer; return the updated rate for ``tier``, B/s."""
        _check_positive("elapsed_s", elapsed_s)
        _check_positive("server_s", server_s, allow_zero=True)
        transfer = max(elapsed_s - server_s, self.min_transfer_s)
        rate = max(bytes_up + bytes_down, 1) / transfer
        old = self._rate.get(tier)
        self._rate[tier] = rate if old is None else self.alpha * rate + (1 - self.alpha) * old
        self._count[tier] += 1
        return self._rate[tier]

    def estimate(self, tier: str, *, remote_hz: float | None = None) -> LinkEstimate | None:
        """The current estimate for ``tier`` (marked measured), or None before any observation."""
        rate = self._rate.get(tier)
        if rate is None:
            return None
        return LinkEstimate(up_Bps=rate, down_Bps=rate, rtt_s=0.0, remote_hz=remote_hz, measured=True)

    def estimates(self, default: LinkEstimate | None = None) -> dict[str, LinkEstimate]:
        """Estimates for every remote tier; unobserved tiers get ``default`` (if given)."""
        out: dict[str, LinkEstimate] = {}
        for tier in REMOTE_TIERS:
            est = self.estimate(tier)
            if est is not None:
                out[tier] = est
            elif default is not None:
                out[tier] = default
        return out

    def observations(self, tier: str) -> int:
        """How many transfers were observed for ``tier``."""
        return self._count[tier]


class EnergyLedger:
    """Per-request robot energy, summed per tier, for fleet and scenario reports."""

    def __init__(self, robot: str, profile_name: str) -> None:
        self.robot = robot
        self.profile_name = profile_name
        self._energy: dict[str, float] = defaultdict(float)
        self._count: dict[str, int] = defaultdict(int)
        self._missed = 0

    def record(self, placement: Placement, *, tier: str | None = None, energy_j: float | None = None) -> None:
        """Add one request.  ``tier``/``energy_j`` override the placement's
        (e.g. when the request finally ran elsewhere after a failover)."""
        t = tier or placement.tier
        self._energy[t] += placement.robot_energy_j if energy_j is None else energy_j
        self._count[t] += 1
        self._missed += int(placement.deadline_missed)

    def summary(self) -> dict[str, Any]:
        """``{"robot", "profile", "total_j", "requests", "deadline_missed", "per_tier": {tier: {"energy_j", "requests"}}}``."""
        return {
            "robot": self.robot,
            "profile": self.profile_name,
            "total_j": sum(self._energy.values()),
            "requests": sum(self._count.values()),
            "deadline_missed": self._missed,
            "per_tier": {t: {"energy_j": self._energy[t], "requests": self._count[t]} for t in sorted(self._energy)},
        }


def energy_by_robot(records: Iterable[Mapping[str, Any]], profiles: Mapping[str, str]) -> dict[str, Any]:
    """Robot energy and where each task ran, per robot, from fleet records (pure).

    Parameters
    ----------
    records : iterable of dict
        The robots' ``records.jsonl`` rows; a robot that ran the energy policy
        (``scmr robot --profile``) writes ``energy_j`` and ``energy`` on each.
    profiles : mapping
        ``{robot: profile name}`` of the robots that were given a profile.

    Returns
    -------
    dict
        ``{robot: {"profile", "total_j", "tasks", "ran": {tier: {"tasks", "energy_j"}},
        "planned_elsewhere", "deadline_missed", "probes", "costed"}}``: ``ran`` counts
        each finished request under the tier that answered it (``failed`` when none
        did); ``planned_elsewhere`` counts the requests that ran on another tier than
        the policy chose (failover); ``costed`` the records that carried ``energy_j``.
    """
    out: dict[str, Any] = {}
    for robot, prof in profiles.items():
        out[robot] = {"profile": prof, "total_j": 0.0, "tasks": 0, "ran": {}, "planned_elsewhere": 0,
                      "deadline_missed": 0, "probes": 0, "costed": 0}
    for r in records:
        robot = str(r.get("robot"))
        if robot not in out:
            continue
        o = out[robot]
        tier = (r.get("tier") or "failed") if r.get("ok") else "failed"
        slot = o["ran"].setdefault(tier, {"tasks": 0, "energy_j": 0.0})
        slot["tasks"] += 1
        o["tasks"] += 1
        if r.get("energy_j") is not None:
            e = float(r["energy_j"])
            slot["energy_j"] += e
            o["total_j"] += e
            o["costed"] += 1
        info = r.get("energy") or {}
        if info.get("planned_tier") is not None and info.get("planned_tier") != tier:
            o["planned_elsewhere"] += 1
        o["deadline_missed"] += int(bool(info.get("deadline_missed")))
        o["probes"] += int(bool(info.get("probe")))
    return out
