"""What ``scmr thesis`` runs: the configuration and the fleet runs as scenarios (pure: starts nothing).

Every fleet run is a scenario of :mod:`scmr_mesh.scenario` (real peers, real faults, the
shared runner), built from the shipped ``peers/scenarios/baseline.toml`` (thesis Table 4.2's
shape: robots with Table 4.3 profiles robot1..robot4, five real images each, 2 Hz):

``noloss``
    experiments 1-3: no fault; every answer should come from the cloud.
``loss``
    experiments 4-6: the robots are cut from the cloud one by one (``link_down robotK-cloud``
    every ``step`` seconds), then the cloud from everyone (a partition), then everything heals;
    each stage has one more robot served by the leader (thesis Figure 4.21 C).
``size<N>``
    Table 4.4: ``N`` robots (profiles and image sets dealt round-robin), the cloud serves the
    first half of the run and is cut from everyone for most of the second (it is back shortly
    before the end, so the telemetry the leader relayed gets stored), so the same run measures
    the robot-to-cloud (R2C) and the robot-to-leader (R2R) delay at fleet size ``N``.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scmr_mesh.errors import InputError

#: The shipped scenario whose image sets and fleet the thesis runs reuse.
BASELINE = Path(__file__).resolve().parents[2] / "peers" / "scenarios" / "baseline.toml"
#: Seconds of start-up and shut-down a fleet run costs besides its duration (measured on the
#: shared 2-core box: servers ready 1-4 s, robots 1-2 s, stop and telemetry count 2-4 s).
RUN_OVERHEAD_S = 9.0
#: Seconds the analysis and figures take (stage images of every frame, plots).
ANALYSIS_S = 15.0
#: Robots send at the thesis's pace of the shipped scenarios.
RATE_HZ = 2.0

QUICK_SIZES = (1, 2, 4)
FULL_SIZES = (1, 2, 4, 8, 16)


@dataclass
class ThesisConfig:
    """What to run.

    Attributes
    ----------
    quick : bool
        Short runs (``step_s`` 2 s, fleet sizes 1, 2, 4): about 2 minutes on a quiet 2-core box.
    robots : int
        Robots of the Table 4.2 runs (1-4: robot1..robotN, Table 4.3 profiles).
    images : int
        Images per robot (1-5, the first of each Table 4.2 set).
    fleet_sizes : tuple of int
        Fleet sizes of the Table 4.4 runs.
    step_s : float
        The time unit of every run (see :func:`plan_runs`).
    backend : str
        ``netns`` (root, kernel-level faults) or ``proxy``.
    data_dir : Path or None
        The road images (default ``$SCMR_DATA`` or ``../shared/data/roads``).
    out : Path
        The report folder.
    """

    quick: bool = False
    robots: int = 4
    images: int = 5
    fleet_sizes: tuple[int, ...] = ()
    step_s: float = 0.0
    backend: str = "proxy"
    data_dir: Path | None = None
    out: Path = Path("runs/thesis")
    rate_hz: float = RATE_HZ
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.fleet_sizes:
            self.fleet_sizes = QUICK_SIZES if self.quick else FULL_SIZES
        if not self.step_s:
            self.step_s = 2.0 if self.quick else 8.0
        self.fleet_sizes = tuple(sorted(set(int(n) for n in self.fleet_sizes)))

    def check(self) -> None:
        """Raise :class:`InputError` naming the bad value and the fix."""
        if not 1 <= self.robots <= 4:
            raise InputError(f"--robots must be 1..4 (Table 4.2 has four robots), got {self.robots}")
        if not 1 <= self.images <= 5:
            raise InputError(f"--images must be 1..5 (Table 4.2 gives each robot five), got {self.images}")
        if len(self.fleet_sizes) < 2 or min(self.fleet_sizes) < 1 or max(self.fleet_sizes) > 32:
            raise InputError(f"--fleet-sizes needs at least two sizes in 1..32 to fit a curve, got "
                             f"{','.join(map(str, self.fleet_sizes))}; e.g. --fleet-sizes 1,2,4")
        if not 0.5 <= self.step_s <= 600:
            raise InputError(f"--step must be 0.5..600 seconds, got {self.step_s:g}")
        if self.backend not in ("netns", "proxy"):
            raise InputError(f"backend must be netns or proxy, got {self.backend!r}")


def load_baseline(path: Path = BASELINE) -> dict[str, Any]:
    """The shipped baseline scenario as a plain dict (image sets, fleet)."""
    try:
        return tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"cannot read the shipped scenario {path}: {exc}") from None


def _robots(base: dict[str, Any], n: int, images: int) -> tuple[list[dict], dict[str, list[str]]]:
    """``n`` robots with Table 4.3 profiles and Table 4.2 image sets dealt round-robin."""
    proto = base["fleet"]["robots"]
    sets = base["image_sets"]
    robots, used = [], {}
    for i in range(n):
        p = proto[i % len(proto)]
        rid = f"robot{i + 1}"
        set_name = p["image_set"]
        used[set_name] = list(sets[set_name][:images])
        robots.append({"id": rid, "profile": p["profile"], "image_set": set_name, "rate_hz": RATE_HZ})
    return robots, used


def _scenario(name: str, description: str, seed: int, duration_s: float, lease_ms: int, robots: list[dict],
              sets: dict[str, list[str]], faults: list[dict], rate_hz: float) -> dict[str, Any]:
    for r in robots:
        r["rate_hz"] = rate_hz
    return {
        "name": name, "description": description, "seed": seed, "duration_s": duration_s, "lease_ms": lease_ms,
        "image_sets": sets,
        "fleet": {"clouds": ["cloud"], "leader": "leader", "robots": robots},
        "faults": faults,
        # the report's verdicts are the thesis's; a run is only refused when nothing was answered
        "expectations": [{"metric": "requests", "op": ">=", "value": 1}],
    }


def plan_runs(config: ThesisConfig, base: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """The fleet runs as scenario dicts (``scmr_mesh.scenario.spec.parse_scenario`` input), in run order.

    With ``T = config.step_s``: ``noloss`` lasts ``4 T``; ``loss`` cuts robot ``k`` from the
    cloud at ``k T`` (k = 1..R), the cloud from everyone at ``R T``, heals at ``(R + 1.5) T`` and
    ends at ``(R + 2.5) T``; ``size<N>`` lasts ``3 T`` with the cloud cut from everyone from
    ``1.5 T`` to ``2.75 T``.

    Examples
    --------
    >>> runs = plan_runs(ThesisConfig(quick=True, robots=2, images=1))
    >>> list(runs), runs["loss"]["duration_s"], [f["at_s"] for f in runs["loss"]["faults"]]
    (['noloss', 'loss', 'size1', 'size2', 'size4'], 9.0, [2.0, 4.0, 4.0])
    """
    base = copy.deepcopy(base if base is not None else load_baseline())
    T, R, K = config.step_s, config.robots, config.images
    out: dict[str, dict[str, Any]] = {}
    robots, sets = _robots(base, R, K)
    out["noloss"] = _scenario(
        "thesis-noloss", "Experiments 1-3: Table 4.2's robots offload to the cloud; no fault.",
        11, 4 * T, 500, robots, sets, [], config.rate_hz)
    robots, sets = _robots(base, R, K)
    heal = (R + 1.5) * T
    faults = [{"kind": "link_down", "at_s": k * T, "for_s": heal - k * T, "link": [f"robot{k}", "cloud"]}
              for k in range(1, R + 1)]
    faults.append({"kind": "partition", "at_s": R * T, "for_s": heal - R * T,
                   "groups": [["cloud"], ["leader"] + [r["id"] for r in robots]]})
    out["loss"] = _scenario(
        "thesis-loss", "Experiments 4-6: the robots lose the cloud one by one, then the leader does too; "
        "the leader serves them; everything heals.", 12, heal + T, 150, robots, sets, faults, config.rate_hz)
    for n in config.fleet_sizes:
        robots, sets = _robots(base, n, K)
        cut = 1.5 * T
        out[f"size{n}"] = _scenario(
            f"thesis-size{n}", f"Table 4.4: {n} robots; the cloud serves until {cut:g} s, then the leader until "
            f"{2.75 * T:g} s.",
            100 + n, 3 * T, 150, robots, sets,
            [{"kind": "partition", "at_s": cut, "for_s": 1.25 * T,
              "groups": [["cloud"], ["leader"] + [r["id"] for r in robots]]}],
            config.rate_hz)
    return out


def estimate_s(config: ThesisConfig, runs: dict[str, dict[str, Any]] | None = None) -> float:
    """Seconds the whole run is expected to take: each run's duration plus start-up and stop, plus analysis."""
    runs = runs if runs is not None else plan_runs(config)
    return sum(float(r["duration_s"]) + RUN_OVERHEAD_S for r in runs.values()) + ANALYSIS_S


def stages(config: ThesisConfig) -> list[dict[str, Any]]:
    """The stages of the ``loss`` run: ``{"k", "from_s", "to_s"}``, ``k`` robots cut from the cloud.

    Stage 0 is before the first cut; stage R lasts until the heal.
    """
    T, R = config.step_s, config.robots
    out = [{"k": 0, "from_s": 0.0, "to_s": T}]
    for k in range(1, R + 1):
        out.append({"k": k, "from_s": k * T, "to_s": (k + 1) * T if k < R else (R + 1.5) * T})
    return out
