"""Energy-aware task placement: local, cloud or leader (thesis 3.5.4, extended).

Policy
------
Among local execution and every *reachable* remote tier (``cloud``,
``leader``) that has a link estimate, choose the option with the least robot
energy whose predicted completion time meets the task's deadline ``T``.  If no
option meets ``T``, choose the fastest and flag ``deadline_missed``.  Ties in
energy go to local execution (the thesis runs locally when ``E_r <= E_c``),
then to the faster option.  An unreachable tier is never chosen.

Predicted times: local ``C / f`` (``f = S_r``, or the DVS clock); remote
``D_up / B_u + C / S_remote + D_down / B_d + rtt``.

DVS (Eq 3.16-3.17): with ``dvs=True`` local execution runs at the lowest clock
level that meets ``T`` (the lowest level when there is no deadline), at
``k * f**2`` J per cycle with ``k = P_c / S_r**3`` (see
:attr:`~scmr_mesh.energy.model.Profile.dvs_k`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from scmr_mesh.energy.model import (
    PROFILES,
    THESIS_F,
    Profile,
    _check_positive,
    e_idle,
    e_proc,
    e_trans,
)
from scmr_mesh.errors import InputError

__all__ = ["REMOTE_TIERS", "Task", "LinkEstimate", "Placement", "energy_terms", "choose_placement"]

log = logging.getLogger(__name__)

#: Remote tiers in the order they are evaluated (``peer``: another robot of the R2R tier).
REMOTE_TIERS = ("cloud", "leader", "peer")
_TASK_FIELDS = ("cycles", "bytes_up", "bytes_down", "deadline_s")


@dataclass(frozen=True)
class Task:
    """One unit of work to place.

    Parameters
    ----------
    cycles : float
        ``C``, CPU cycles the task needs (e.g. from
        :func:`~scmr_mesh.energy.measure.cycles_from_cpu_time`).
    bytes_up : int
        ``D_up``, request size in bytes.
    bytes_down : int
        ``D_down``, reply size in bytes.
    deadline_s : float or None
        ``T``, delay deadline in s; None means no deadline.
    measured : frozenset of str
        Which of ``cycles``, ``bytes_up``, ``bytes_down``, ``deadline_s`` were
        measured (the rest are assumed); reports mark each input.
    """

    cycles: float
    bytes_up: int
    bytes_down: int
    deadline_s: float | None = None
    measured: frozenset[str] = field(default=frozenset())

    def __post_init__(self) -> None:
        _check_positive("Task.cycles", self.cycles)
        _check_positive("Task.bytes_up", self.bytes_up, allow_zero=True)
        _check_positive("Task.bytes_down", self.bytes_down, allow_zero=True)
        if self.deadline_s is not None:
            _check_positive("Task.deadline_s", self.deadline_s)
        unknown = set(self.measured) - set(_TASK_FIELDS)
        if unknown:
            raise InputError(
                f"Task.measured names unknown fields {sorted(unknown)}; use any of {list(_TASK_FIELDS)}"
            )
        object.__setattr__(self, "measured", frozenset(self.measured))


@dataclass(frozen=True)
class LinkEstimate:
    """What the robot knows about its link to one remote tier.

    Parameters
    ----------
    up_Bps, down_Bps : float
        ``B_u``, ``B_d``: upload and download rates, bytes/s.
    rtt_s : float
        Round-trip latency added to every remote request, s.
    remote_hz : float or None
        Clock of the serving tier, Hz.  None: the cloud is ``F * S_r`` (thesis
        assumption), the leader is the ``leader`` profile's clock.
    measured : bool
        True when the rates come from observed transfers, False when assumed.
    """

    up_Bps: float
    down_Bps: float
    rtt_s: float = 0.0
    remote_hz: float | None = None
    measured: bool = False

    def __post_init__(self) -> None:
        _check_positive("LinkEstimate.up_Bps", self.up_Bps)
        _check_positive("LinkEstimate.down_Bps", self.down_Bps)
        _check_positive("LinkEstimate.rtt_s", self.rtt_s, allow_zero=True)
        if self.remote_hz is not None:
            _check_positive("LinkEstimate.remote_hz", self.remote_hz)


@dataclass(frozen=True)
class Placement:
    """The decision for one task, with every option considered.

    Attributes
    ----------
    tier : {"local", "cloud", "leader"}
        Where to run the task.
    robot_energy_j : float
        Predicted robot energy of the chosen option, J.
    predicted_s : float
        Predicted completion time of the chosen option, s.
    deadline_missed : bool
        True when no option meets the deadline (the fastest was chosen).
    reason : str
        One sentence explaining the choice and any tier left out.
    options : list of dict
        Per evaluated option: ``tier``, ``robot_energy_j``, ``predicted_s``,
        ``meets_deadline`` and the energy terms.
    inputs : dict
        Each model input with its value, unit and ``source``
        (``"measured"`` or ``"assumed"``).
    """

    tier: str
    robot_energy_j: float
    predicted_s: float
    deadline_missed: bool
    reason: str
    options: list[dict[str, Any]]
    inputs: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "tier": self.tier,
            "robot_energy_j": self.robot_energy_j,
            "predicted_s": self.predicted_s,
            "deadline_missed": self.deadline_missed,
            "reason": self.reason,
            "options": self.options,
            "inputs": self.inputs,
        }


def _remote_hz(tier: str, profile: Profile, link: LinkEstimate, cloud_factor: float) -> float:
    if link.remote_hz is not None:
        return link.remote_hz
    if tier == "leader":
        return PROFILES["leader"].clock_hz
    if tier == "peer":  # a robot like this one, unless its load message said its clock
        return profile.clock_hz
    return cloud_factor * profile.clock_hz


def energy_terms(
    task: Task,
    profile: Profile,
    link: LinkEstimate,
    *,
    tier: str = "cloud",
    cloud_factor: float = THESIS_F,
) -> dict[str, float]:
    """The Eq 4.2-4.6 terms for running ``task`` locally vs on one remote tier.

    Parameters
    ----------
    task : Task
    profile : Profile
        The robot's profile (``P_c, P_i, P_u, P_d, S_r``).
    link : LinkEstimate
        Link to the remote tier.
    tier : {"cloud", "leader"}
        Which remote tier (sets the default remote clock).
    cloud_factor : float
        ``F`` in ``S_c = F * S_r`` when the link gives no ``remote_hz``.

    Returns
    -------
    dict
        ``e_proc_j``, ``e_idle_j``, ``e_trans_j``, ``e_cloud_j``
        (= idle + trans), ``e_saved_j`` (= proc - cloud), ``remote_hz``,
        ``local_s`` and ``remote_s`` (predicted times).

    Examples
    --------
    >>> from scmr_mesh.energy import PROFILES
    >>> t = energy_terms(Task(5e9, 1048576, 1048576), PROFILES["robot1"],
    ...                  LinkEstimate(3014656, 3670016))
    >>> round(t["e_proc_j"], 3), round(t["e_idle_j"], 4)
    (235.0, 0.4167)
    """
    if tier not in REMOTE_TIERS:
        raise InputError(f"tier must be one of {list(REMOTE_TIERS)}, got {tier!r}")
    remote_hz = _remote_hz(tier, profile, link, cloud_factor)
    proc = e_proc(task.cycles, p_compute_w=profile.p_compute_w, clock_hz=profile.clock_hz)
    idle = e_idle(task.cycles, p_idle_w=profile.p_idle_w, remote_hz=remote_hz, rtt_s=link.rtt_s)
    trans = e_trans(
        task.bytes_up,
        task.bytes_down,
        p_up_w=profile.p_up_w,
        p_down_w=profile.p_down_w,
        up_Bps=link.up_Bps,
        down_Bps=link.down_Bps,
    )
    remote_s = (
        task.bytes_up / link.up_Bps + task.cycles / remote_hz + task.bytes_down / link.down_Bps + link.rtt_s
    )
    return {
        "e_proc_j": proc,
        "e_idle_j": idle,
        "e_trans_j": trans,
        "e_cloud_j": idle + trans,
        "e_saved_j": proc - (idle + trans),
        "remote_hz": remote_hz,
        "local_s": task.cycles / profile.clock_hz,
        "remote_s": remote_s,
    }


def _meets(t: float, deadline: float | None) -> bool:
    return deadline is None or t <= deadline


def _local_option(task: Task, profile: Profile, dvs: bool) -> dict[str, Any]:
    if not dvs:
        t = task.cycles / profile.clock_hz
        return {
            "tier": "local",
            "robot_energy_j": e_proc(task.cycles, p_compute_w=profile.p_compute_w, clock_hz=profile.clock_hz),
            "predicted_s": t,
            "meets_deadline": _meets(t, task.deadline_s),
            "clock_hz": profile.clock_hz,
            "dvs": False,
        }
    levels = profile.dvs_levels()
    ok = [f for f in levels if _meets(task.cycles / f, task.deadline_s)]
    f = ok[0] if ok else levels[-1]
    t = task.cycles / f
    return {
        "tier": "local",
        "robot_energy_j": task.cycles * profile.dvs_k * f * f,
        "predicted_s": t,
        "meets_deadline": _meets(t, task.deadline_s),
        "clock_hz": f,
        "dvs": True,
    }


def _inputs(
    task: Task, profile: Profile, links: Mapping[str, LinkEstimate], tiers: list[str], cloud_factor: float
) -> dict[str, dict[str, Any]]:
    def mark(value: Any, unit: str, measured: bool) -> dict[str, Any]:
        return {"value": value, "unit": unit, "source": "measured" if measured else "assumed"}

    out = {
        "cycles": mark(task.cycles, "cycles", "cycles" in task.measured),
        "bytes_up": mark(task.bytes_up, "B", "bytes_up" in task.measured),
        "bytes_down": mark(task.bytes_down, "B", "bytes_down" in task.measured),
        "deadline_s": mark(task.deadline_s, "s", "deadline_s" in task.measured),
        "profile": mark(profile.name, f"({profile.source})", False),
        "p_compute_w": mark(profile.p_compute_w, "W", False),
        "p_idle_w": mark(profile.p_idle_w, "W", False),
        "p_up_w": mark(profile.p_up_w, "W", False),
        "p_down_w": mark(profile.p_down_w, "W", False),
        "clock_hz": mark(profile.clock_hz, "Hz", False),
    }
    for tier in tiers:
        link = links[tier]
        out[f"{tier}.up_Bps"] = mark(link.up_Bps, "B/s", link.measured)
        out[f"{tier}.down_Bps"] = mark(link.down_Bps, "B/s", link.measured)
        out[f"{tier}.rtt_s"] = mark(link.rtt_s, "s", link.measured)
        out[f"{tier}.remote_hz"] = mark(_remote_hz(tier, profile, link, cloud_factor), "Hz", False)
    if "cloud" in tiers and links["cloud"].remote_hz is None:
        out["cloud_factor"] = mark(cloud_factor, "F = S_c / S_r", False)
    return out


def choose_placement(
    task: Task,
    profile: Profile,
    *,
    reachable: Iterable[str],
    links: Mapping[str, LinkEstimate],
    dvs: bool = False,
    cloud_factor: float = THESIS_F,
) -> Placement:
    """Choose where to run ``task`` to spend the least robot energy.

    Parameters
    ----------
    task : Task
        Cycles, request/reply bytes and optional deadline.
    profile : Profile
        The deciding robot's power profile.
    reachable : iterable of str
        Remote tiers reachable right now (``"cloud"``, ``"leader"``; from the
        live liveliness view).  ``"local"`` may be included and is ignored:
        local execution is always possible.  Tiers not listed are never chosen.
    links : mapping of str to LinkEstimate
        Link estimate per remote tier.  A reachable tier without one is left
        out (and named in ``reason``).
    dvs : bool
        Run local execution at the lowest sufficient DVS clock (Eq 3.16-3.17).
    cloud_factor : float
        ``F``: the cloud's clock is ``F * S_r`` unless the link says otherwise.

    Returns
    -------
    Placement

    Raises
    ------
    InputError
        When ``reachable`` names an unknown tier.

    Examples
    --------
    >>> from scmr_mesh.energy import PROFILES
    >>> p = choose_placement(Task(5e9, 1048576, 1048576), PROFILES["robot1"],
    ...                      reachable=["cloud"], links={"cloud": LinkEstimate(3014656, 3670016)})
    >>> p.tier
    'cloud'
    """
    reach = set(reachable)
    unknown = reach - set(REMOTE_TIERS) - {"local"}
    if unknown:
        raise InputError(
            f"reachable names unknown tiers {sorted(unknown)}; use any of {list(REMOTE_TIERS)}"
        )
    options = [_local_option(task, profile, dvs)]
    left_out: list[str] = []
    evaluated: list[str] = []
    for tier in REMOTE_TIERS:
        if tier not in reach:
            left_out.append(f"{tier} not reachable")
            continue
        link = links.get(tier)
        if link is None:
            left_out.append(f"{tier} has no link estimate")
            continue
        terms = energy_terms(task, profile, link, tier=tier, cloud_factor=cloud_factor)
        evaluated.append(tier)
        options.append(
            {
                "tier": tier,
                "robot_energy_j": terms["e_cloud_j"],
                "predicted_s": terms["remote_s"],
                "meets_deadline": _meets(terms["remote_s"], task.deadline_s),
                "e_idle_j": terms["e_idle_j"],
                "e_trans_j": terms["e_trans_j"],
                "remote_hz": terms["remote_hz"],
            }
        )
    order = {o["tier"]: i for i, o in enumerate(options)}
    feasible = [o for o in options if o["meets_deadline"]]
    if feasible:
        best = min(feasible, key=lambda o: (o["robot_energy_j"], o["predicted_s"], order[o["tier"]]))
        missed = False
        others = [o for o in options if o is not best]
        why = f"{best['tier']}: least robot energy ({best['robot_energy_j']:.4g} J"
        if others:
            why += "; " + ", ".join(
                f"{o['tier']} {o['robot_energy_j']:.4g} J" + ("" if o["meets_deadline"] else " (misses deadline)")
                for o in others
            )
        why += ")"
        if task.deadline_s is not None:
            why += f", meets deadline {task.deadline_s:.4g} s (predicted {best['predicted_s']:.4g} s)"
    else:
        best = min(options, key=lambda o: (o["predicted_s"], o["robot_energy_j"], order[o["tier"]]))
        missed = True
        why = (
            f"{best['tier']}: no option meets deadline {task.deadline_s:.4g} s; "
            f"chose the fastest (predicted {best['predicted_s']:.4g} s, {best['robot_energy_j']:.4g} J)"
        )
    if left_out:
        why += "; " + "; ".join(left_out)
    placement = Placement(
        tier=best["tier"],
        robot_energy_j=float(best["robot_energy_j"]),
        predicted_s=float(best["predicted_s"]),
        deadline_missed=missed,
        reason=why,
        options=options,
        inputs=_inputs(task, profile, links, evaluated, cloud_factor),
    )
    log.debug("placement %s: %s", profile.name, why)
    return placement
