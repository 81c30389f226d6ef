"""The robot energy model of thesis 4.3 (Eq 4.2-4.6), in SI units.

Every quantity is in SI units: cycles, Hz (cycles/s), bytes, bytes/s, W, J, s.

* Local execution (Eq 4.2): ``E_proc = P_c * C / S_r``.
* Offloaded execution, robot side (Eq 4.3-4.4, 4.8):
  ``E_idle = P_i * C / S_c`` with ``S_c = F * S_r`` (cloud) or the serving
  tier's clock, and ``E_trans = P_u * D_up / B_u + P_d * D_down / B_d``;
  ``E_cloud = E_idle + E_trans``.
* ``E_saved = E_proc - E_cloud`` (Eq 4.5-4.6); offloading saves robot energy
  when ``E_saved > 0``.

Extension (documented in docs/ENERGY.md): the robot also idles for the
round-trip time ``rtt`` of a remote request, so ``E_idle = P_i * (C / S_c +
rtt)``.  With ``rtt = 0`` (the default and the thesis's case) this is Eq 4.3.

The thesis writes ``C = 5`` "instructions" against clocks in GHz; we read it as
``C = 5e9`` cycles against clocks in Hz, which gives the same seconds.

References
----------
Thesis "Survivable Cloud Multi-Robotics Framework for Heterogeneous
Environments", sections 3.5 and 4.3, Table 4.3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = [
    "THESIS_F",
    "THESIS_CYCLES",
    "MIB",
    "THESIS_MBPS",
    "Profile",
    "PROFILES",
    "e_proc",
    "e_idle",
    "e_trans",
    "break_even_up_Bps",
]

#: Client/server performance ratio F of the thesis (``S_c = F * S_r``).
THESIS_F = 300.0
#: The thesis's C = 5 "instructions" read as 5e9 cycles (clocks are in GHz).
THESIS_CYCLES = 5e9
#: The thesis's "1 MB" (Eq 4.9 uses D = 1048576 bytes).
MIB = 1048576
#: Bytes/s per the thesis's "Mb/s" (Eq 4.9: 23 Mb/s = 3014656 B/s, i.e. 2**20 bit/s).
THESIS_MBPS = 131072

#: Default DVS clock ladder as fractions of the nominal clock (an assumption:
#: typical P-state span of the Table 4.3 CPUs; override with ``dvs_levels_hz``).
DEFAULT_DVS_FRACTIONS = (0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


@dataclass(frozen=True)
class Profile:
    """Power and clock parameters of one robot (a column of thesis Table 4.3).

    Parameters
    ----------
    name : str
        Profile name (``leader``, ``robot1`` ... or a user name).
    p_compute_w : float
        ``P_c``, average power while computing, W.
    p_idle_w : float
        ``P_i``, average power while idle (waiting for a remote result), W.
    p_up_w : float
        ``P_u``, power while uploading, W.
    p_down_w : float
        ``P_d``, power while downloading, W.
    clock_hz : float
        ``S_r``, the robot's CPU clock, Hz.
    description : str
        Free text (the CPU model for Table 4.3 profiles).
    dvs_levels_hz : tuple of float
        Clocks the CPU can run at under DVS, Hz.  Empty means the default
        ladder ``clock_hz * (0.4, 0.5, ..., 1.0)``.
    source : str
        Where the profile came from (``thesis Table 4.3`` or a file path).
    """

    name: str
    p_compute_w: float
    p_idle_w: float
    p_up_w: float
    p_down_w: float
    clock_hz: float
    description: str = ""
    dvs_levels_hz: tuple[float, ...] = field(default=())
    source: str = "thesis Table 4.3"

    @property
    def dvs_k(self) -> float:
        """Effective switched capacitance ``k`` of Eq 3.16, J/cycle/Hz^2.

        Derived so that the DVS energy per cycle ``k * f**2`` equals the
        Eq 4.2 energy per cycle ``P_c / S_r`` at the nominal clock:
        ``k = P_c / S_r**3``.
        """
        return self.p_compute_w / self.clock_hz**3

    def dvs_levels(self) -> tuple[float, ...]:
        """The DVS clock levels in Hz, ascending, never above ``clock_hz``."""
        levels = self.dvs_levels_hz or tuple(f * self.clock_hz for f in DEFAULT_DVS_FRACTIONS)
        return tuple(sorted({min(float(x), self.clock_hz) for x in levels}))

    def to_dict(self) -> dict:
        """JSON-ready parameters."""
        return {
            "name": self.name,
            "p_compute_w": self.p_compute_w,
            "p_idle_w": self.p_idle_w,
            "p_up_w": self.p_up_w,
            "p_down_w": self.p_down_w,
            "clock_hz": self.clock_hz,
            "description": self.description,
            "dvs_levels_hz": list(self.dvs_levels()),
            "source": self.source,
        }


def _table_4_3() -> dict[str, Profile]:
    rows = [
        ("leader", 177.0, 99.0, 314.61, 391.98, 3.5e9, "Intel Core i7-3770"),
        ("robot1", 47.0, 25.0, 83.54, 104.08, 1.0e9, "Intel Pentium"),
        ("robot2", 83.0, 37.0, 147.53, 183.80, 2.3e9, "Core 2 Quad Q8200S"),
        ("robot3", 93.0, 38.0, 165.31, 205.95, 2.5e9, "Core 2 Quad E8500"),
        ("robot4", 106.0, 39.0, 188.41, 234.74, 2.83e9, "Core 2 Quad Q9550S"),
    ]
    return {r[0]: Profile(*r) for r in rows}


#: The built-in profiles of thesis Table 4.3, by name.
PROFILES: dict[str, Profile] = _table_4_3()


def _check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        from scmr_mesh.errors import InputError

        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        from scmr_mesh.errors import InputError

        bound = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name} must be a finite number {bound}, got {value!r}")
    return v


def e_proc(cycles: float, *, p_compute_w: float, clock_hz: float) -> float:
    """Energy to run a task locally (Eq 4.2), J.

    Parameters
    ----------
    cycles : float
        ``C``, CPU cycles the task needs.
    p_compute_w : float
        ``P_c``, W.
    clock_hz : float
        ``S_r``, Hz.

    Returns
    -------
    float
        ``P_c * C / S_r`` in J.

    Examples
    --------
    >>> e_proc(5e9, p_compute_w=47.0, clock_hz=1e9)
    235.0
    """
    return p_compute_w * cycles / clock_hz


def e_idle(cycles: float, *, p_idle_w: float, remote_hz: float, rtt_s: float = 0.0) -> float:
    """Robot energy while it waits for a remote tier (Eq 4.3, plus rtt), J.

    ``P_i * (C / S_c + rtt)``; with ``rtt_s = 0`` this is Eq 4.3.

    Examples
    --------
    >>> round(e_idle(5e9, p_idle_w=25.0, remote_hz=300e9), 6)
    0.416667
    """
    return p_idle_w * (cycles / remote_hz + rtt_s)


def e_trans(
    bytes_up: float,
    bytes_down: float,
    *,
    p_up_w: float,
    p_down_w: float,
    up_Bps: float,
    down_Bps: float,
) -> float:
    """Robot energy to upload the request and download the reply (Eq 4.4), J.

    ``P_u * D_up / B_u + P_d * D_down / B_d``.

    Examples
    --------
    >>> e_trans(1000, 500, p_up_w=2.0, p_down_w=4.0, up_Bps=100.0, down_Bps=1000.0)
    22.0
    """
    return p_up_w * bytes_up / up_Bps + p_down_w * bytes_down / down_Bps


def break_even_up_Bps(
    profile: Profile,
    *,
    cycles: float,
    bytes_up: float,
    bytes_down: float,
    down_up_ratio: float = 1.0,
    cloud_factor: float = THESIS_F,
) -> float:
    """Upload bandwidth at which offloading to the cloud breaks even, B/s.

    With ``B_d = down_up_ratio * B_u``, ``E_saved(B_u) = 0`` has the closed form

    ``B_u* = (P_u * D_up + P_d * D_down / r) / ((C / S_r) * (P_c - P_i / F))``.

    Offloading saves energy for every ``B_u > B_u*``.  Returns ``inf`` when it
    never saves (``P_c <= P_i / F``) and ``0.0`` when nothing is transferred.
    """
    margin = (cycles / profile.clock_hz) * (profile.p_compute_w - profile.p_idle_w / cloud_factor)
    cost = profile.p_up_w * bytes_up + profile.p_down_w * bytes_down / down_up_ratio
    if cost == 0:
        return 0.0 if margin > 0 else math.inf
    if margin <= 0:
        return math.inf
    return cost / margin
