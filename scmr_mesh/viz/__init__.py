"""The rerun viewer: red/green overlays and QoS time lines of a fleet run.

This is the only package of scmr-mesh that imports ``rerun``, and it does so
inside functions: a command run without rerun flags never imports rerun and
never starts or writes anything rerun-related.

Modules, lowest first (each imports only those above it):

==============  ==============================================================
``common``      ids, ports, class colours, entity roots, :class:`ViewerError`
``rerun_cli``   the ``rerun`` executable with analytics off; reading ``.rrd``
``options``     ``--save/--spawn/--serve/--connect`` and :class:`RerunOptions`
``sink``        the one gRPC sink every process of a run logs into
``recording``   per-process streams and :class:`RobotViz` (a robot's logger)
``blueprint``   the viewer layout, in code
``fleet``       :class:`FleetViz`: the fleet process's side
``screenshot``  headless screenshots of recordings
``commands``    ``scmr view``
==============  ==============================================================

Public names are imported lazily (``from scmr_mesh.viz import RerunOptions``
costs no rerun import).

How the pieces fit
------------------
* Fleet commands (``scmr up``, ``scmr scenario run``, ``scmr demo``) call
  :func:`add_rerun_args` (``--save FILE.rrd | --spawn | --serve | --connect [URL]``)
  and :meth:`RerunOptions.from_args`; with a flag they start a
  :class:`FleetViz`, which opens the *sink* once and hands each child peer
  :meth:`FleetViz.child_args` (``--rerun-url URL --rerun-recording-id ID``).
* Peers (robot, cloud, leader) call :func:`add_rerun_peer_args` and
  :meth:`RerunOptions.from_args`; a robot opens a :class:`RobotViz` and passes
  :meth:`RobotViz.observe` to ``add_observer``.
* Every process logs into ONE recording: application id :data:`APP_ID` and the
  recording id chosen by the fleet process.  The sink is one gRPC endpoint all
  processes connect to:

  ==========  ===========================================================
  flag        sink started by the fleet process
  ==========  ===========================================================
  --save F    a headless ``rerun --save`` gRPC server (child process); at
              the end it is stopped and its stream is finalised into F with
              ``rerun rrd merge`` (adds the footer ``rrd verify`` wants)
  --spawn     a native viewer ``rerun --port P`` (left running at the end)
  --serve     ``rerun --serve-web`` (gRPC + web viewer on 127.0.0.1)
  --connect   nothing: the viewer at URL is the sink
  ==========  ===========================================================

* rerun's usage analytics are off for every rerun process the project starts:
  they get :func:`rerun_env` (``XDG_CONFIG_HOME``/``XDG_DATA_HOME`` pointing to
  :func:`state_dir`, holding an ``analytics.json`` with analytics disabled), so
  nothing is read from or written to the user's ``~/.config/rerun``.  The
  logging SDK itself (``save``/``connect_grpc``) writes no analytics (checked
  by ``tests/test_viz_analytics.py``).

Entity paths mirror :mod:`scmr_mesh.keys`:

====================================  ==========================================
entity                                content
====================================  ==========================================
``scmr/robot``                        static AnnotationContext (1 green, 2 red)
``scmr/robot/<r>/camera``             camera frame (JPEG), resized to the map
``scmr/robot/<r>/camera/drivable``    drivability map, SegmentationImage
``scmr/robot/<r>/srm``                SRM image (optional)
``scmr/results/<r>/tor_ms``           time of response of each ok request
``scmr/results/<r>/tier``             serving tier as a level (:data:`TIER_LEVEL`)
``scmr/results/<r>/ror``              RoR of this robot so far
``scmr/results/<r>/log``              one text line per request
``scmr/telemetry/<r>/battery``        battery level
``scmr/telemetry/<r>/energy_j``       energy spent per request (J)
``scmr/alive/<role>/<node>``          1 while the liveliness token is up, else 0
``scmr/faults/<target>``              1 while a scenario fault is on, else 0
``scmr/faults/log``                   fault start/end markers (text log)
``scmr/fleet/ror``                    fleet RoR so far
====================================  ==========================================

Time lines: ``wall_time`` (timestamp) on everything, ``request`` (sequence,
the robot's request number) on per-request data.
"""

from __future__ import annotations

from scmr_mesh._lazy import lazy_exports

_EXPORTS = {
    "APP_ID": "common",
    "CLASSES": "common",
    "DEFAULT_CONNECT_URL": "common",
    "DEFAULT_PORT": "common",
    "DEFAULT_WEB_PORT": "common",
    "ENV_RECORDING_ID": "common",
    "ENV_SAVE_DIR": "common",
    "ENV_URL": "common",
    "TIER_LEVEL": "common",
    "ViewerError": "common",
    "entity_name": "common",
    "check_rrd": "rerun_cli",
    "rerun_env": "rerun_cli",
    "rerun_executable": "rerun_cli",
    "rrd_rows": "rerun_cli",
    "run_rerun_cli": "rerun_cli",
    "state_dir": "rerun_cli",
    "RerunOptions": "options",
    "add_rerun_args": "options",
    "add_rerun_peer_args": "options",
    "check_reachable": "options",
    "has_display": "options",
    "normalize_url": "options",
    "RobotViz": "recording",
    "robot_viz": "recording",
    "_mask_to_classes": "recording",
    "fleet_blueprint": "blueprint",
    "FleetViz": "fleet",
    "fleet_viz": "fleet",
    "peers_env_session": "fleet",
}

__all__ = sorted(n for n in _EXPORTS if not n.startswith("_"))

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
