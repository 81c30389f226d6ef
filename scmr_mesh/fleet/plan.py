"""What a fleet run starts: :class:`FleetConfig` and :func:`plan_fleet` (pure: starts nothing).

A topology declared first and turned into processes later (STYLE.md, from
mininet): :func:`plan_fleet` maps a config and ports to one
:class:`~scmr_mesh.fleet.procs.PeerSpec` per peer.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scmr_mesh.errors import InputError

if TYPE_CHECKING:
    from scmr_mesh.scenario.plan import RunOptions
    from scmr_mesh.scenario.spec import Scenario

log = logging.getLogger(__name__)

CLOUD, LEADER = "cloud", "leader"
#: Most cloud nodes ``scmr up --clouds`` starts on one host.
MAX_CLOUDS = 16
#: Values of ``--ods-backend``.
ODS_BACKENDS = ("auto", "sqlite", "postgresql")
#: File that marks a folder as an scmr run directory (``scmr demo`` only replaces such folders).
RUN_MARKER = ".scmr-run"
#: Written in ``RUN/ready/`` once every peer of the fleet is ready; robots start sending when it appears.
FLEET_READY = "fleet.ready"



@dataclass
class FleetConfig:
    """What to run.

    Attributes
    ----------
    robots : int
        Number of robot peers (besides the leader).
    clouds : int
        Number of cloud nodes (``cloud0`` ... ``cloud<N-1>``); robots spread
        their frames over them by published load.
    ods_backend : {"auto", "sqlite", "postgresql"}
        The cloud nodes' shared data store: ``auto`` is SQLite
        (``<run dir>/ods.sqlite``) for one cloud node and a PostgreSQL server
        started for the run (``<run dir>/postgres``) for several.
    ods : str or None
        An existing store instead (a SQLite file or a ``postgresql://`` URL):
        nothing is started for it.
    duration_s : float
        How long each robot sends frames.
    rate_hz : float
        Frames per second per robot.
    cloud_outage : (float, float) or None
        Seconds after the fleet is ready at which the cloud tier (every cloud
        node) is SIGKILLed and restarted.
    kill_cloud : (int, float) or None
        ``(i, t)``: SIGKILL cloud node ``cloud<i>`` ``t`` seconds after the
        fleet is ready and leave it down (the other nodes serve on; needs
        ``clouds > 1`` to keep the cloud tier).
    images : Path or None
        A folder of images every robot sends (else synthetic scenes).
    synthetic : sequence of str
        Synthetic scene kinds, dealt to the robots round-robin (empty: all
        kinds the imaging package offers).
    run_dir : Path or None
        Where logs, records and the report go (default ``runs/<timestamp>``).
    workers : int or None
        Worker processes of the cloud and the leader (default: theirs).
    lease_ms, deadline_ms : int or None
        Passed to the peers when set.
    server_args, robot_args : sequence of str
        Extra arguments for cloud+leader and for robots.
    ready_timeout_s : float
        How long a peer may take to write its ready file.
    rerun : scmr_mesh.viz.RerunOptions or None
        Show or record the run in rerun (``--save/--spawn/--serve/--connect``);
        ``None``: nothing rerun-related happens.
    bootstrap : str
        The one peer every robot (and the leader) is handed to connect to:
        ``cloud`` (default), ``leader`` or a robot id; gossip scouting finds
        every other peer (docs/R2R.md).
    leader_capable : int or None
        The first N robots run for the lead of the R2R tier (``--leader-capable``)
        and serve other robots while they do not lead (default: two, or every
        robot of a smaller fleet).
    leader_crash_s : float or None
        Seconds after the fleet is ready at which whichever node leads is
        SIGKILLed (not restarted).
    profiles : sequence of str
        Energy profiles dealt to the robots round-robin (``--profiles``: Table
        4.3's robot1..robot4 by default); each robot then runs ``--profile
        NAME`` and the energy model places its frames (docs/ENERGY.md).
        Empty (the default): no energy model, robots offload every frame.
    shape : {"auto", "clique", "routers"}
        How the peers link (``--shape``): ``routers`` runs one zenoh router for the host and every
        peer as its client (docs/R2R.md "Multi-hop"); ``auto`` is the clique up to
        :data:`CLIQUE_MAX_ROBOTS` robots and routers above (:func:`fleet_shape`).
    insecure : bool
        Run the fleet without authentication (``--insecure``).  By default a
        development CA and one certificate per peer are made in
        ``<run dir>/certs`` and every peer runs mutual TLS with the fleet's
        access rules (docs/SECURITY.md).
    """

    robots: int = 4
    clouds: int = 1
    ods_backend: str = "auto"
    ods: str | None = None
    duration_s: float = 10.0
    rate_hz: float = 5.0
    cloud_outage: tuple[float, float] | None = None
    kill_cloud: tuple[int, float] | None = None
    images: Path | None = None
    synthetic: Sequence[str] = ()
    run_dir: Path | None = None
    workers: int | None = None
    lease_ms: int | None = None
    deadline_ms: int | None = None
    server_args: Sequence[str] = ()
    robot_args: Sequence[str] = ()
    ready_timeout_s: float = 90.0
    python: str = sys.executable
    rerun: Any = None
    bootstrap: str = CLOUD
    leader_capable: int | None = None
    leader_crash_s: float | None = None
    profiles: Sequence[str] = ()
    insecure: bool = False
    #: ``--mcap FILE``: every robot records its frames and masks, merged into FILE when the run ends.
    mcap: str | None = None
    #: ``topology.shape`` of the fleet's scenario: ``auto``, ``clique`` or ``routers`` (one router for the host).
    shape: str = "auto"
    #: Robots played by one ``scmr swarm`` process (``--robots-per-process``; 1: a process each).
    robots_per_process: int = 1

    def check(self) -> None:
        """Raise :class:`InputError` naming the bad value and the fix."""
        if self.robots < 1:
            raise InputError(f"--robots must be at least 1, got {self.robots}")
        if not 1 <= self.clouds <= MAX_CLOUDS:
            raise InputError(f"--clouds must be between 1 and {MAX_CLOUDS}, got {self.clouds}")
        if self.ods_backend not in ODS_BACKENDS:
            raise InputError(f"--ods-backend must be one of {', '.join(ODS_BACKENDS)}, got {self.ods_backend!r}")
        if self.ods is not None and self.ods_backend != "auto":
            raise InputError("give either --ods (an existing store) or --ods-backend (a store started for the "
                             "run), not both")
        if not self.duration_s > 0:
            raise InputError(f"--duration must be positive (seconds), got {self.duration_s}")
        if not self.rate_hz > 0:
            raise InputError(f"--rate must be positive (Hz), got {self.rate_hz}")
        if self.cloud_outage is not None:
            start, end = self.cloud_outage
            if not 0 <= start < end <= self.duration_s:
                raise InputError(
                    f"--cloud-outage must satisfy 0 <= START < END <= --duration ({self.duration_s:g}), "
                    f"got {start:g}:{end:g}"
                )
        if self.kill_cloud is not None:
            i, t = self.kill_cloud
            if not 0 <= i < self.clouds or not 0 <= t <= self.duration_s:
                raise InputError(f"--kill-cloud must name cloud0..cloud{self.clouds - 1} at 0..{self.duration_s:g} s "
                                 f"(--duration), got cloud{i}@{t:g}")
            if self.cloud_outage is not None:
                raise InputError("give either --kill-cloud or --cloud-outage, not both")
        if self.images is not None and not Path(self.images).is_dir():
            raise InputError(f"--images must be a folder of images, got {self.images} (not a folder)")
        if self.leader_crash_s is not None and not 0 <= self.leader_crash_s < self.duration_s:
            raise InputError(f"--leader-crash must be within 0 <= S < --duration ({self.duration_s:g}), "
                             f"got {self.leader_crash_s:g}")
        if self.leader_capable is not None and not 0 <= self.leader_capable <= self.robots:
            raise InputError(f"--leader-capable must be between 0 and --robots ({self.robots}), "
                             f"got {self.leader_capable}")
        names = [c for c, _ in cloud_peers(self.clouds)] + [LEADER] + robot_ids(self.robots)
        if self.bootstrap not in names:
            raise InputError(f"--bootstrap must name a peer of the fleet ({', '.join(names[:6])}...), "
                             f"got {self.bootstrap!r}")
        if self.bootstrap in robot_ids(self.robots):
            raise InputError(f"--bootstrap {self.bootstrap}: robots start after the servers, so the servers "
                             "could not reach it; use cloud or leader (scenarios can chain robots)")
        if self.profiles:
            from scmr_mesh.energy import PROFILES

            unknown = [p for p in self.profiles if p not in PROFILES]
            if unknown:
                raise InputError(f"--profiles: unknown profile {unknown[0]!r}; use Table 4.3 names "
                                 f"({', '.join(PROFILES)}), e.g. --profiles robot1,robot4")

    @property
    def capable_robots(self) -> int:
        """How many robots run for the lead (``leader_capable``, default min(2, robots))."""
        return min(2, self.robots) if self.leader_capable is None else self.leader_capable


#: Table 4.3 profiles dealt to leader-capable robots (as their election capability), best first.
CAPABILITY_PROFILES = ("robot4", "robot3", "robot2", "robot1")
#: Table 4.3 robot profiles ``scmr up --profiles`` deals to robots r1, r2, ... round-robin.
TABLE_4_3_ROBOTS = ("robot1", "robot2", "robot3", "robot4")


def robot_profiles(config: FleetConfig) -> dict[str, str]:
    """Each robot's energy profile (``{}`` without ``--profiles``): dealt round-robin.

    Examples
    --------
    >>> robot_profiles(FleetConfig(robots=5, profiles=TABLE_4_3_ROBOTS))["r5"]
    'robot1'
    """
    ps = list(config.profiles)
    return {rid: ps[i % len(ps)] for i, rid in enumerate(robot_ids(config.robots))} if ps else {}


def fleet_topology(config: FleetConfig) -> dict[str, dict[str, Any]]:
    """Each peer's role, what it is handed to connect to, and whether it runs for the lead (pure).

    Every cloud node listens; the leader and every robot are handed the one
    bootstrap peer (``config.bootstrap``; the leader, when it is the
    bootstrap itself, is handed the first cloud), so each finds the rest by
    gossip scouting.  Leader-capable robots rank by a Table 4.3 profile
    (:data:`CAPABILITY_PROFILES`, best first); the dedicated leader by the
    thesis's leader profile.

    Examples
    --------
    >>> t = fleet_topology(FleetConfig(robots=3, leader_capable=1))
    >>> t["r1"], t["r3"]["connect"]
    ({'role': 'robot', 'connect': ['cloud'], 'leader_capable': True, 'capability': 'robot4'}, ['cloud'])
    """
    out: dict[str, dict[str, Any]] = {}
    for i, (name, _node) in enumerate(cloud_peers(config.clouds)):  # cloud1.. join through the first
        out[name] = {"role": "cloud", "connect": [] if i == 0 else [CLOUD], "leader_capable": False,
                     "capability": None}
    leader_boot = config.bootstrap if config.bootstrap != LEADER else CLOUD
    out[LEADER] = {"role": "leader", "connect": [leader_boot], "leader_capable": True, "capability": "leader"}
    for i, rid in enumerate(robot_ids(config.robots)):
        capable = i < config.capable_robots
        out[rid] = {"role": "robot", "connect": [config.bootstrap], "leader_capable": capable,
                    "capability": CAPABILITY_PROFILES[i % len(CAPABILITY_PROFILES)] if capable else None}
    return out


def fleet_identities(config: FleetConfig):
    """The identities a secured fleet needs (pure): node names, roles and lead grants.

    Cloud nodes ``cloud0``.., the dedicated leader ``leader0`` (role leader), and the
    robots, leader-capable ones with ``+leader-capable`` (they run for the lead).

    >>> [p.spec() for p in fleet_identities(FleetConfig(robots=2, leader_capable=1))]
    ['cloud0=cloud', 'leader0=leader', 'r1=robot+leader-capable', 'r2=robot']
    """
    from scmr_mesh.security.credentials import Peer

    topo = fleet_topology(config)
    out = [Peer(node, "cloud") for _name, node in cloud_peers(config.clouds)]
    out.append(Peer("leader0", "leader", leader_capable=True, priority_cap=0))
    for rid in robot_ids(config.robots):
        out.append(Peer(rid, "robot", leader_capable=bool(topo[rid]["leader_capable"]), priority_cap=0))
    return out


def parse_outage(text: str) -> tuple[float, float]:
    """``"8:14"`` -> ``(8.0, 14.0)`` (seconds after the fleet is ready)."""
    try:
        a, b = str(text).split(":")
        start, end = float(a), float(b)
    except ValueError:
        raise InputError(f"--cloud-outage must be START:END in seconds such as 8:14, got {text!r}") from None
    if not 0 <= start < end:
        raise InputError(f"--cloud-outage needs 0 <= START < END, got {text!r}")
    return start, end


def parse_kill(text: str) -> tuple[int, float]:
    """``"cloud2@5"`` -> ``(2, 5.0)``: which cloud node to SIGKILL, seconds after the fleet is ready."""
    import re

    m = re.fullmatch(r"cloud(\d+)@(\d+(?:\.\d*)?)", str(text).strip())
    if not m:
        raise InputError(f"--kill-cloud must be cloudI@SECONDS such as cloud1@5, got {text!r}")
    return int(m.group(1)), float(m.group(2))


def _default_kinds() -> list[str]:
    try:
        from scmr_mesh.imaging.synthetic import SCENE_KINDS
    except ImportError:  # pragma: no cover - imaging not built yet
        return ["road"]
    return list(SCENE_KINDS)


def robot_ids(n: int) -> list[str]:
    """Robot ids of a fleet of ``n``: ``r1`` ... ``rn``."""
    return [f"r{i}" for i in range(1, n + 1)]


def cloud_peers(n: int) -> list[tuple[str, str]]:
    """``(peer name, node name)`` of ``n`` cloud nodes: ``("cloud", "cloud0")``, ``("cloud1", "cloud1")``...

    The first keeps the peer name ``cloud`` (``logs/cloud.log``, ``ready/cloud.ready``)
    that one-cloud fleets always had.
    """
    return [(CLOUD if i == 0 else f"cloud{i}", f"cloud{i}") for i in range(n)]


def ods_backend(config: FleetConfig) -> str:
    """The data store backend a fleet runs with: ``sqlite`` or ``postgresql``."""
    if config.ods is not None:
        from scmr_mesh.data.ods import is_dsn

        return "postgresql" if is_dsn(config.ods) else "sqlite"
    if config.ods_backend == "auto":
        return "sqlite" if config.clouds == 1 else "postgresql"
    return config.ods_backend


def fleet_scenario(config: FleetConfig) -> "Scenario":
    """``scmr up``'s flags as a :class:`~scmr_mesh.scenario.spec.Scenario` (pure).

    The fleet runs on the one scenario engine: ``--cloud-outage A:B`` is a
    crash of every cloud node at A restarted at B, ``--kill-cloud cloudI@T`` a
    crash of that node at T that stays down, ``--leader-crash S`` a crash of
    whoever leads at S (:data:`~scmr_mesh.scenario.spec.WHOEVER_LEADS`), also
    left down.  Peers keep their fleet names (``cloud``, ``cloud1``, ``leader``,
    ``r1``...) and run as nodes ``cloud0``.., ``leader0`` and the robot ids.

    Examples
    --------
    >>> sc = fleet_scenario(FleetConfig(robots=2, cloud_outage=(6, 10), leader_crash_s=8, duration_s=20))
    >>> [(f.kind, f.at_s, f.for_s, f.crashed, f.restart) for f in sc.faults]
    [('crash', 6.0, 4.0, ('cloud',), True), ('crash', 8.0, None, ('@leader',), False)]
    >>> sc.node_of("cloud"), sc.node_of("leader"), sc.bootstraps["r2"]
    ('cloud0', 'leader0', ('cloud',))
    """
    from scmr_mesh.mesh.config import DEFAULT_LEASE_MS
    from scmr_mesh.scenario.spec import WHOEVER_LEADS, Fault, RobotSpec, Scenario

    topo = fleet_topology(config)
    clouds = cloud_peers(config.clouds)
    kinds = list(config.synthetic) or _default_kinds()
    profiles = robot_profiles(config)
    robots = []
    for i, rid in enumerate(robot_ids(config.robots)):
        t = topo[rid]
        robots.append(RobotSpec(
            id=rid, profile=profiles.get(rid), energy_placement=rid in profiles,
            images=str(config.images) if config.images is not None else None,
            synthetic=None if config.images is not None else kinds[i % len(kinds)],
            rate_hz=float(config.rate_hz), deadline_ms=config.deadline_ms,
            leader_capable=bool(t["leader_capable"]), capability=t["capability"]))
    faults = []
    if config.cloud_outage is not None:
        a, b = config.cloud_outage
        faults.append(Fault("crash", at_s=float(a), for_s=float(b) - float(a),
                            peers=tuple(name for name, _ in clouds)))
    if config.kill_cloud is not None:
        i, t = config.kill_cloud
        faults.append(Fault("crash", at_s=float(t), peer=clouds[i][0], restart=False))
    if config.leader_crash_s is not None:
        faults.append(Fault("crash", at_s=float(config.leader_crash_s), peer=WHOEVER_LEADS, restart=False))
    names = [name for name, _ in clouds] + [LEADER] + [r.id for r in robots]
    return Scenario(
        name="fleet", seed=0, duration_s=float(config.duration_s), robots=tuple(robots),
        clouds=tuple(name for name, _ in clouds), leader=LEADER,
        lease_ms=int(config.lease_ms if config.lease_ms is not None else DEFAULT_LEASE_MS),
        description=f"scmr up: {config.clouds} cloud node(s), a leader and {config.robots} robots on loopback",
        links=tuple((names[i], names[j]) for i in range(len(names)) for j in range(i)),
        faults=tuple(sorted(faults, key=lambda f: f.at_s)), source="scmr up",
        bootstraps={n: tuple(topo[n]["connect"]) for n in names},
        node_names={**{name: node for name, node in clouds}, LEADER: "leader0"}, shape=fleet_shape(config))


#: ``scmr up --shape auto`` keeps the clique up to this many robots.  Measured on this 2-core box:
#: the clique held 32 robots (p99 109 ms) and broke at 48 (the cloud served 27 of 2,705 frames);
#: at 64 it served none and lost every telemetry record, where one router for the host served
#: 1,498 of 1,789 remotely and lost 5 (docs/BENCHMARKS.md "One host, many robots").
CLIQUE_MAX_ROBOTS = 32


def fleet_shape(config: FleetConfig) -> str:
    """The fleet's ``topology.shape``: ``--shape``, or for ``auto`` the clique up to
    :data:`CLIQUE_MAX_ROBOTS` robots and one router for the host above.

    >>> fleet_shape(FleetConfig(robots=4)), fleet_shape(FleetConfig(robots=64))
    ('clique', 'routers')
    """
    if config.shape != "auto":
        return config.shape
    return "clique" if config.robots <= CLIQUE_MAX_ROBOTS else "routers"


def fleet_options(config: FleetConfig, *, ods: str | None = None) -> "RunOptions":
    """How ``scmr up`` starts its peers (pure): ``-v`` logs, its extra arguments, one name per peer."""
    from scmr_mesh.scenario.plan import RunOptions

    return RunOptions(python=config.python, verbose=True, robot_quiet=False, robot_seed=False,
                      workers=config.workers, server_args=tuple(config.server_args),
                      robot_args=tuple(config.robot_args), ods=ods if ods is not None else config.ods,
                      start_file=FLEET_READY, restart_renames=False,
                      robots_per_process=config.robots_per_process)


def plan_fleet(config: FleetConfig, run_dir: Path, ports: Mapping[str, int], *, ods: str | None = None,
               security: Sequence[str] = ()):
    """The peers of a fleet as :class:`~scmr_mesh.fleet.procs.PeerSpec` (pure: starts nothing).

    What the engine starts for ``scmr up``: :func:`fleet_scenario` and
    :func:`fleet_options` through the one command-line builder
    (:func:`scmr_mesh.scenario.plan.peer_command`), on loopback ``ports``.

    Returns
    -------
    dict
        ``{name: PeerSpec}``, servers first (clouds, then the leader).  Each
        peer is handed its bootstrap (:func:`fleet_topology`), then the peers
        started before it (``Scenario.dials``: Zenoh re-dials only those after a
        cut); gossip scouting links it to the others.
    """
    from scmr_mesh.fleet.procs import PeerSpec
    from scmr_mesh.scenario.plan import peer_command

    sc = fleet_scenario(config)
    options = fleet_options(config, ods=ods)

    def ep(name: str) -> str:
        return f"tcp/127.0.0.1:{ports[name]}"

    specs = {}
    for p in sc.peers:
        cmd = peer_command(sc, p.name, run_dir=run_dir, listen=[ep(p.name)],
                           connect=[ep(b) for b in sc.dials(p.name)], security=security,
                           options=options)
        specs[p.name] = PeerSpec(p.name, list(cmd.argv), log_path=cmd.log_path, ready_file=cmd.ready_file)
    return specs
