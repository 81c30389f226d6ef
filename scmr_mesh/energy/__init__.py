"""Energy model and energy-aware task placement (thesis 3.5, 4.3; pure core).

No Zenoh, no rerun: the robot peer, reports and the ``scmr energy`` commands
all call this package.  SI units throughout (cycles, Hz, bytes, bytes/s, W, J).

Public API
----------
Profile, PROFILES, get_profile, load_profiles
    Robot power profiles (thesis Table 4.3 plus user TOML files).
Task, LinkEstimate, Placement, choose_placement, energy_terms
    The model (Eq 4.2-4.6) and the placement policy (3.5.4, extended, with
    optional DVS, Eq 3.16-3.17).
cycles_from_cpu_time, host_clock_hz, LinkEstimator, EnergyLedger
    Measured inputs and per-tier energy accounting.
"""

from scmr_mesh.energy.measure import (
    EnergyLedger,
    LinkEstimator,
    cycles_from_cpu_time,
    host_clock_hz,
)
from scmr_mesh.energy.model import (
    MIB,
    PROFILES,
    THESIS_CYCLES,
    THESIS_F,
    THESIS_MBPS,
    Profile,
    break_even_up_Bps,
)
from scmr_mesh.energy.placement import (
    LinkEstimate,
    Placement,
    Task,
    choose_placement,
    energy_terms,
)
from scmr_mesh.energy.profiles import get_profile, load_profiles

__all__ = [
    "MIB",
    "PROFILES",
    "THESIS_CYCLES",
    "THESIS_F",
    "THESIS_MBPS",
    "EnergyLedger",
    "LinkEstimate",
    "LinkEstimator",
    "Placement",
    "Profile",
    "Task",
    "break_even_up_Bps",
    "choose_placement",
    "cycles_from_cpu_time",
    "energy_terms",
    "get_profile",
    "host_clock_hz",
    "load_profiles",
]
