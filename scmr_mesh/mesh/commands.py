"""``scmr cloud | leader | robot | ros | router | swarm``: the mesh peers, one OS process each; ``scmr tap``.

Contract (other areas start these as processes; ``python -m scmr_mesh <cmd>``
works too)::

    scmr cloud  --node NAME [--listen EP ...] [--connect EP ...] [--workers N]
                [--config FILE] [--cfg KEY:JSON5 ...] [--lease-ms MS]
                [--ready-file PATH] [--mode best|thesis] [--log-file PATH]
    scmr leader --node NAME (same flags as cloud) [robot flags: also a robot]
    scmr robot  --id ID (--images DIR | --synthetic KIND) [--rate HZ]
                [--count N | --duration S] --out DIR [--deadline-ms MS]
                [--redundant] [--hedge-ms auto|off|MS] [--local-fallback/--no-local-fallback]
                [--listen/--connect/--config/--cfg/--lease-ms] [--ready-file PATH]
    scmr router [--listen EP ...] [--connect EP ...] [--config/--cfg]
    scmr ros    --id ID --image-topic TOPIC [--compressed] [--mask-topic TOPIC] [--domain N]
                [--ros-connect EP] --out DIR [--rate HZ] [robot and mesh flags] (docs/ROS2.md)
    scmr swarm  --plan PLAN [--ready-file PATH]   (several robots in one process: a load generator)
    scmr tap    KEYEXPR [--get] [--count N] [--duration S] [--id NAME] (--security ... | --insecure)

SIGTERM/SIGINT stop a peer cleanly (exit 0).  Logs go to stderr or
``--log-file``.  See docs/protocol.md for keys and messages.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

from scmr_mesh import cliargs as ca
from scmr_mesh.data.retention import DEFAULT_KEEP_MASKS
from scmr_mesh.mesh.data_agent import MEMORY_BUFFER_BYTES
from scmr_mesh.errors import InputError, MeshError, ScmrError
from scmr_mesh.mesh.resources import appeared

log = logging.getLogger(__name__)

_PEER_EPILOG = """\
Security: a peer refuses to start without --security PROFILE (mutual TLS and the fleet's
access rules: peers/secure/mtls.toml with --credentials DIR from `scmr certs`) unless
--insecure is given.  `scmr up`, `scmr demo` and `scmr scenario run` make credentials for
their peers themselves (docs/SECURITY.md).

Zenoh defaults (docs/ZENOH.md): multicast scouting off, gossip on, lease 500 ms
with 4 keep-alives, a dead endpoint retried every 50 ms.  Give peers explicit endpoints,
e.g. cloud --listen tcp/127.0.0.1:7447, robots --connect tcp/127.0.0.1:7447.
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``cloud``, ``leader``, ``robot``, ``ros`` and ``router`` to ``scmr``."""
    from scmr_mesh.mesh import config

    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser(
        "cloud", help="run a cloud node: the drivable-region service (R2C tier)", formatter_class=fmt,
        description="Serve drivable-region requests on scmr/drivable/cloud/NODE with a pool of worker "
                    "processes, hold the liveliness token scmr/alive/cloud/NODE and publish load on "
                    "scmr/load/cloud/NODE.  Runs until SIGTERM/SIGINT.",
        epilog=_PEER_EPILOG)
    _service_args(p)
    config.add_arguments(p)
    _data_args(p, "cloud")
    p.set_defaults(func=_cmd_cloud)

    p = sub.add_parser(
        "leader", help="run a dedicated leader candidate of the R2R tier, optionally also a robot",
        formatter_class=fmt,
        description="A leader-capable node of the R2R tier (docs/R2R.md), ranked by --capability "
                    "(default: the thesis's leader profile, 3.5 GHz).  Leadership is a role: the node "
                    "runs in the election with every other candidate (robots started with "
                    "--leader-capable); while elected it serves drivable-region requests on "
                    "scmr/drivable/leader/NODE (token scmr/alive/leader/NODE) and the leader's data "
                    "tier; otherwise it serves robots on scmr/drivable/peer/NODE and keeps a copy of "
                    "the leader's data buffer.  With --images or --synthetic (and --out) it is also a "
                    "robot with id NODE.",
        epilog=_PEER_EPILOG)
    _service_args(p)
    _r2r_args(p, robot=False)
    _robot_args(p, leader=True)
    config.add_arguments(p)
    _data_args(p, "leader")
    p.set_defaults(func=_cmd_leader)

    p = sub.add_parser(
        "robot", help="run a robot: send frames to the mesh, record results", formatter_class=fmt,
        description="Send frames (a folder of images or synthetic scenes) as requests to the cloud, "
                    "falling back to the leader and then to local execution, by the live view of "
                    "liveliness tokens.  Writes OUT/outbox, OUT/inbox/<seq>.mask.png and "
                    "OUT/records.jsonl (one JSON object per request), and prints a JSON summary "
                    "on stdout at the end.  A reply is used only when it echoes the request's robot, "
                    "seq and frame digest; any other is counted (mismatched) and never used.  Exits 1 "
                    "when telemetry was lost or a reply was mismatched.",
        epilog=_PEER_EPILOG)
    _robot_command_args(p)
    p.set_defaults(func=_cmd_robot)

    p = sub.add_parser(
        "ros", help="run a robot whose camera is a ROS 2 topic on rmw_zenoh: masks go back as ROS images",
        formatter_class=fmt,
        description="A ROS 2 robot gets drivable-region masks with no code (docs/ROS2.md).  Joining the ROS "
                    "graph through its Zenoh router (rmw_zenohd, --ros-connect) as an rmw_zenoh node does "
                    "(--ros-mode) it subscribes to --image-topic "
                    "(sensor_msgs/msg/Image, or CompressedImage JPEG/PNG with --compressed), sends each frame "
                    "through the scmr tiers like `scmr robot` (cloud, leader, peers, local; same failover, "
                    "security, records and telemetry) and publishes the mask as sensor_msgs/msg/Image mono8 "
                    "(255 = drivable, the input's size, stamp and frame_id) on --mask-topic and an rgb8 "
                    "overlay on MASK_TOPIC/overlay, with rmw_zenoh's attachment and liveliness tokens "
                    "(`ros2 node list` shows scmr_ros_ID).  Frames arriving faster than they are served are "
                    "dropped oldest-first and counted; samples that are not an 8-bit image are counted by "
                    "reason and logged once per topic.  Prints a JSON summary on stdout at the end; exits 1 "
                    "when samples were rejected, frames got no mask, telemetry was lost or a reply did not "
                    "answer its request (mismatched).",
        epilog=_PEER_EPILOG)
    p.add_argument("--id", required=True, help="robot id (A-Z a-z 0-9 _ . -)")
    r = p.add_argument_group("ROS 2 side")
    r.add_argument("--domain", type=ca.count("ROS domain id", lo=0, hi=232, example="0"), default=0, metavar="N",
                   help="ROS_DOMAIN_ID of the ROS graph (default 0)")
    r.add_argument("--image-topic", required=True, metavar="TOPIC", help="camera topic, e.g. /camera/image_raw")
    r.add_argument("--compressed", action="store_true",
                   help="the topic carries sensor_msgs/msg/CompressedImage (jpeg or png) instead of Image")
    r.add_argument("--mask-topic", default="/drivable/mask", metavar="TOPIC",
                   help="where masks go (mono8); the overlay goes to TOPIC/overlay (default /drivable/mask)")
    r.add_argument("--ros-connect", action="append", default=[], metavar="EP",
                   help="endpoint of the ROS side's Zenoh router (default tcp/localhost:7447, where rmw_zenohd "
                        "listens; waited for up to 30 s, then exit 1); repeat for several")
    r.add_argument("--ros-mode", choices=("auto", "peer", "client"), default="auto",
                   help="how the bridge joins the ROS graph: peer, as an rmw_zenoh node does (the router for "
                        "discovery only, frames and masks directly to and from the ROS nodes, which accept "
                        "links on loopback); client (every sample through the router: for a router on another "
                        "host); auto (default): peer when every --ros-connect is on loopback, else client")
    r.add_argument("--ros-cfg", action="append", default=[], metavar="KEY:JSON5",
                   help="zenoh config override for the ROS session only, e.g. TLS to the ROS router")
    r.add_argument("--ros-shm", action=argparse.BooleanOptionalAction, default=False,
                   help="offer zenoh shared memory on the ROS session (default off, as in rmw_zenoh's config): "
                        "frames and masks then go through /dev/shm with ROS nodes that enable it too "
                        "(rmw_zenoh's transport/shared_memory/enabled); the frames' hop is ~1 ms shorter, but "
                        "the time to mask was not (docs/ROS2.md)")
    r.add_argument("--node-name", default=None, metavar="NAME",
                   help="ROS node name (default scmr_ros_ID, characters ROS refuses written _)")
    g = p.add_argument_group("robot")
    g.add_argument("--out", type=ca.PathArg("out-dir"), metavar="DIR", required=True,
                   help="output folder (outbox, inbox, records.jsonl), as for `scmr robot`")
    g.add_argument("--rate", type=ca.positive("frames per second", hi=10000, example="5"), default=None, metavar="HZ",
                   help="at most HZ frames per second go to the mesh (default: as fast as they are served)")
    g.add_argument("--count", type=ca.count("frames", lo=0, hi=10**9, example="100"), default=None, metavar="N",
                   help="stop after N frames served or failed")
    g.add_argument("--mcap", type=ca.PathArg("out-file"), metavar="FILE", default=None,
                   help="also write each frame and mask to FILE.mcap, as `scmr robot --mcap` does")
    g.add_argument("--jpeg-quality", type=ca.count("JPEG quality (0 sends PNG)", lo=0, hi=100, example="90"),
                   default=90, metavar="Q", help="raw Image frames go to the mesh as JPEG at Q (default 90; 0: PNG); "
                                                 "compressed frames go as they are")
    g.add_argument("--full-frames", action="store_true",
                   help="send raw Image frames at full size; by default they are first area-averaged by the "
                        "factor the service decodes them at (640x480 goes as 320x240; the service works on "
                        "300x225 either way, the mask comes back at the input's size)")
    g.add_argument("--deadline-ms", type=ca.Number(lo=0, lo_open=True, hi=3600000, what="milliseconds", example="1000"),
                   default=1000.0, metavar="MS", help="per-attempt deadline (default 1000)")
    g.add_argument("--redundant", action="store_true", help="send each frame to cloud and leader at once")
    g.add_argument("--hedge-ms", type=ca.parsed(_hedge_ms, what="auto, off or milliseconds", example="40"),
                   default="auto", metavar="auto|off|MS", help="hedged requests, as for `scmr robot`")
    g.add_argument("--local-fallback", action=argparse.BooleanOptionalAction, default=True,
                   help="run the pipeline here when no tier answers (default on)")
    g.add_argument("--priority", type=ca.count("priority", lo=0, hi=1000000, example="10"), default=0,
                   help="request priority, default 0")
    g.add_argument("--mode", choices=("best", "thesis"), default="best", help="pipeline mode (default best)")
    g.add_argument("--process", default=None, metavar="MODULE:FUNC",
                   help="process function for local execution (default: the drivable pipeline)")
    g.add_argument("--wait-ms", type=ca.non_negative("milliseconds", hi=3600000, example="2000"), default=2000.0,
                   metavar="MS", help="before serving, wait up to MS for a cloud or leader to appear (default 2000)")
    g.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH",
                   help="written once both sessions are open, the ROS entities declared and the robot warmed up")
    p.add_argument("--log-file", type=ca.PathArg("out-file"), metavar="PATH", help="log here instead of stderr")
    config.add_arguments(p)
    _data_args(p, "robot")
    p.set_defaults(func=_cmd_ros)

    p = sub.add_parser(
        "router", help="run a zenoh router linking sites (fleets across hosts)", formatter_class=fmt,
        description="A zenoh router (a session in router mode).  Across hosts, run one router per "
                    "site, connect each robot, leader and cloud node (peers, the default --zmode) to "
                    "its own site's router and the routers to each other; see docs/DEPLOY.md "
                    "(Routers and endpoints) and docs/ZENOH.md section 6.  Under --security the "
                    "router presents the certificate of --node (a router identity: scmr certs --peers "
                    "router0=router,...) and enforces the fleet's access rules on its links.",
        epilog=_PEER_EPILOG)
    p.add_argument("--node", default=None, help="router name: its identity in the credentials (with --security)")
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH", help="written once the router runs")
    p.add_argument("--log-file", type=ca.PathArg("out-file"), metavar="PATH", help="log here instead of stderr")
    config.add_arguments(p)
    p.set_defaults(func=_cmd_router)

    p = sub.add_parser(
        "tap", help="print every scmr message on a key expression, decoded (an operator's z_sub/z_get)",
        formatter_class=fmt,
        description="Subscribe to KEYEXPR (and with --get also query it) and print one JSON line per "
                    "message: key, kind, size in bytes and the message decoded from msgpack (or JSON); "
                    "binary fields show as their length, a payload that decodes as neither as its first "
                    "bytes in hex.  It sees what the peer it connects to publishes (peers do not forward: "
                    "connect it to that node, or to a router) and what its identity may see under the "
                    "fleet's access rules.  Exit 0; 1 when --count was given and fewer messages came "
                    "before --duration ended.",
        epilog="Example: scmr tap 'scmr/load/**' --security peers/secure/mtls.toml --credentials certs "
               "--id ops --connect tls/127.0.0.1:7447 --count 5\n\n" + _PEER_EPILOG)
    p.add_argument("keyexpr", metavar="KEYEXPR", help="zenoh key expression, e.g. 'scmr/load/**'")
    p.add_argument("--get", action="store_true", help="also query KEYEXPR once and print the replies")
    p.add_argument("--count", type=ca.count("messages", hi=10**9, example="10"), default=None, metavar="N",
                   help="stop after N messages (default: no limit)")
    p.add_argument("--duration", type=ca.positive("seconds", hi=10**7, example="5"), default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--id", default=None, metavar="NAME",
                   help="the operator's identity: the name of its certificate in the credentials (with --security)")
    config.add_arguments(p)
    p.set_defaults(func=_cmd_tap)

    p = sub.add_parser(
        "swarm", help="play several robots from one process (a load generator for benchmarks)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the robots of --plan in this one process.  Each member is a whole robot "
                    "(the arguments of one `scmr robot`): its own zenoh session and identity, frames, "
                    "records, telemetry and ready file.  Writes --ready-file once every member is "
                    "ready; exits 1 when a member failed, lost telemetry or got a mismatched reply.  Members cannot be "
                    "leader-capable.",
        epilog="PLAN is JSON: {\"robots\": [[\"--id\", \"r1\", \"--synthetic\", \"road\", \"--out\", "
               "\"run/r1\", ...], ...]}, each entry one robot's `scmr robot` arguments.  "
               "`scmr up --robots-per-process K` writes these plans itself.")
    p.add_argument("--plan", required=True, type=ca.PathArg("in-file"), metavar="PLAN",
                   help="JSON file with each member's `scmr robot` arguments")
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH",
                   help="written once every member is ready")
    p.set_defaults(func=_cmd_swarm)


def _robot_command_args(p: argparse.ArgumentParser) -> None:
    """Every flag of ``scmr robot`` (also how ``scmr swarm`` reads each member's arguments)."""
    from scmr_mesh.mesh import config

    p.add_argument("--id", required=True, help="robot id (A-Z a-z 0-9 _ . -)")
    _robot_args(p, leader=False)
    _r2r_args(p, robot=True)
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH", help="written once the robot is connected, sees a cloud or leader (or --wait-ms ran out) and is warmed up")
    p.add_argument("--log-file", type=ca.PathArg("out-file"), metavar="PATH", help="log here instead of stderr")
    config.add_arguments(p)
    _data_args(p, "robot")


def _service_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--node", required=True, help="node name (A-Z a-z 0-9 _ . -)")
    p.add_argument("--workers", type=ca.count("worker processes", hi=256), default=None, metavar="N",
                   help="worker processes running the pipeline (default: the cores this process may use: its affinity (taskset), capped by a cgroup CPU quota such as docker --cpus, rounded down)")
    p.add_argument("--mode", choices=("best", "thesis"), default=None,
                   help="default pipeline mode (requests carry their own; kept for symmetry with robots)")
    p.add_argument("--budget-ms", type=ca.positive("milliseconds", hi=3600000, example="60"), default=None,
                   metavar="MS",
                   help="answer 'busy' at once when every worker is busy and a request would spend longer than "
                        "MS here (queue wait predicted from the recent time per frame, plus its own); robots then "
                        "use the leader, a peer or run it locally (default 60; without --queue)")
    p.add_argument("--max-request-bytes", type=ca.count("bytes", hi=1 << 30, example="33554432"), default=None, metavar="N",
                   help="larger requests get an 'oversized' error reply (default 32 MiB); zenoh's transport "
                        "drops any message over this + 8 MiB (default 40 MiB) before it reaches Python")
    p.add_argument("--process", default=None, metavar="MODULE:FUNC",
                   help="process function run by the workers (default: the drivable pipeline; tests "
                        "use scmr_mesh.mesh.testing:stub_process)")
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH",
                   help="written once the service is serving (JSON; 'startup' holds the start-up phases)")
    p.add_argument("--log-file", type=ca.PathArg("out-file"), metavar="PATH", help="log here instead of stderr")
    p.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                   help="more log output, and the start-up phases when ready: wall and CPU ms of each "
                        "from exec (same as scmr -v)")
    from scmr_mesh.mesh import negotiation

    negotiation.add_arguments(p)


def _r2r_args(p: argparse.ArgumentParser, *, robot: bool) -> None:
    """Flags of a leader-capable node (docs/R2R.md)."""
    g = p.add_argument_group("R2R tier (leadership is a role; docs/R2R.md)")
    if robot:
        g.add_argument("--leader-capable", action="store_true",
                       help="run for the lead of the R2R tier: fork a warm worker pool, serve other robots "
                            "on scmr/drivable/peer/ID while another node leads, take the lead when elected")
        g.add_argument("--workers", type=ca.count("worker processes", hi=256, example="1"), default=1, metavar="N",
                       help="with --leader-capable: worker processes of its pool (default 1)")
        g.add_argument("--max-request-bytes", type=ca.count("bytes", hi=1 << 31, example="33554432"), default=None,
                       metavar="N",
                       help="with --leader-capable: larger requests get an 'oversized' error (default 32 MiB)")
    g.add_argument("--capability", metavar="PROFILE", default=None,
                   help="energy profile whose clock and power rank this node in the election (Table 4.3 "
                        "names or --profiles-file); default: " + ("--profile, else this host's measured clock "
                                                                  "with unknown power" if robot else "leader"))
    g.add_argument("--serve-peers", action=argparse.BooleanOptionalAction, default=True,
                   help="serve other robots on the peer tier while not leading (default on)")
    g.add_argument("--leadership-log", type=ca.PathArg("out-file"), metavar="FILE",
                   help="append this node's role changes here as JSON lines (default "
                        "RUN/leadership/NODE.jsonl when a run dir is known, else OUT/leadership.jsonl)")


def _capability(args, *, default: str | None):
    from scmr_mesh.mesh.election import Capability

    name = args.capability or getattr(args, "profile", None) or default
    return Capability.from_profile(name, profiles_file=getattr(args, "profiles_file", None))


def _leadership_log(args, node: str) -> Path | None:
    from scmr_mesh.mesh.data_service import _run_dir_from

    if args.leadership_log:
        return Path(args.leadership_log)
    run_dir = _run_dir_from(args)
    if run_dir is not None:
        return run_dir / "leadership" / f"{node}.jsonl"
    if getattr(args, "out", None):
        return Path(args.out) / "leadership.jsonl"
    return None


def _candidate_data_dir(args, node: str) -> Path | None:
    """The relay queue folder of a candidate's data tier (None: data tier off)."""
    from scmr_mesh.mesh.data_service import _run_dir_from, data_tier_off

    if data_tier_off():
        return None
    if getattr(args, "relay_dir", None):
        return Path(args.relay_dir)
    return (_run_dir_from(args) or Path("runs")) / f"relay-{node}"


def _run_candidate(args, node: str, *, capability_default: str | None, workers, body) -> int:
    from scmr_mesh.mesh.peers import run_candidate
    from scmr_mesh.mesh import negotiation

    capability = _capability(args, default=capability_default)
    return run_candidate(node, _mesh(args), capability=capability, workers=workers, process=args.process,
                         max_request_bytes=args.max_request_bytes, ready_file=args.ready_file, robot_body=body,
                         setup=negotiation.chain(_policy_setup(args), negotiation.service_setup(args)),
                         serve_peers=args.serve_peers,
                         data_dir=_candidate_data_dir(args, node), sync_period_s=getattr(args, "sync_period", 1.0),
                         events_path=_leadership_log(args, node), verbose=bool(getattr(args, "verbose", 0)),
                         budget_ms=getattr(args, "budget_ms", None))


def _robot_args(p: argparse.ArgumentParser, *, leader: bool) -> None:
    g = p.add_argument_group("robot" + (" (optional: makes the leader a robot too)" if leader else ""))
    src = g.add_mutually_exclusive_group(required=not leader)
    src.add_argument("--images", type=ca.PathArg("in-dir", what="a folder of PNG/JPEG frames"), metavar="DIR", help="folder of PNG/JPEG frames (cycled in name order)")
    src.add_argument("--synthetic", metavar="KIND",
                     help="synthetic scenes of this kind (seeded per frame); 'stub' needs no imaging module")
    src.add_argument("--bag", type=ca.PathArg("in-path", what="a rosbag2 folder, .db3 or .mcap file"), metavar="FILE",
                     help="replay a ROS 2 recording (rosbag2 folder, .db3 or .mcap) as the camera, cycled; "
                          "with --topic (docs/ROS2.md)")
    g.add_argument("--topic", metavar="TOPIC", default=None,
                   help="with --bag: the sensor_msgs/msg/Image or CompressedImage topic to replay, e.g. "
                        "/camera/image_raw")
    g.add_argument("--rate", type=ca.positive("frames per second", hi=10000, example="5"), default=5.0, metavar="HZ", help="frames per second (default 5)")
    g.add_argument("--jpeg-quality", type=ca.count("JPEG quality (0 sends PNG)", lo=0, hi=100, example="90"), default=90, metavar="Q",
                   help="frames are sent as JPEG at this quality, 1..100 (default 90); 0 sends lossless PNG. "
                        "JPEG files from --images are sent as they are")
    lim = g.add_mutually_exclusive_group()
    lim.add_argument("--count", type=ca.count("frames", lo=0, hi=10**9, example="100"), default=None, metavar="N", help="stop after N frames")
    lim.add_argument("--duration", type=ca.non_negative("seconds", hi=604800, example="10"), default=None, metavar="S", help="stop after S seconds")
    g.add_argument("--out", type=ca.PathArg("out-dir"), metavar="DIR", required=not leader, help="output folder (outbox, inbox, records.jsonl)")
    g.add_argument("--mcap", type=ca.PathArg("out-file"), metavar="FILE", default=None,
                   help="also write each frame (CompressedImage jpeg) and mask (Image mono8) to FILE.mcap, which "
                        "ROS 2 tools and Foxglove open (docs/ROS2.md)")
    g.add_argument("--deadline-ms", type=ca.Number(lo=0, lo_open=True, hi=3600000, what="milliseconds", example="1000"), default=1000.0, metavar="MS",
                   help="per-attempt deadline; past it the request is re-sent to the next tier (default 1000)")
    g.add_argument("--redundant", action="store_true",
                   help="send each frame to cloud and leader at once; the first good reply wins")
    g.add_argument("--hedge-ms", type=ca.parsed(_hedge_ms, what="auto, off or milliseconds", example="40"),
                   default="auto", metavar="auto|off|MS",
                   help="hedged requests: when the preferred tier has not answered within the hedge delay, send "
                        "the same frame to the next live tier and keep the first good answer; 'auto' (default) "
                        "learns the delay per tier (recent p95 + 20 ms, at least 30 ms, 150 ms before 5 answers) "
                        "and hedges sooner a copy whose node sent no receipt within p95 + 10 ms (at least 20 ms) "
                        "of its receipts; MS fixes the delay (no receipts asked), 'off' waits for the deadline as "
                        "before (docs/R2R.md, Hedged requests)")
    g.add_argument("--local-fallback", action=argparse.BooleanOptionalAction, default=True,
                   help="run the pipeline on the robot when no tier answers (default on)")
    g.add_argument("--priority", type=ca.count("priority", lo=0, hi=1000000, example="10"), default=0, help="request priority (willingness to pay), default 0")
    g.add_argument("--profile", metavar="NAME", default=None,
                   help="energy profile (leader, robot1..robot4, or from --profiles-file): place each frame on "
                        "local/cloud/leader by least robot energy within --deadline-ms and record energy_j per "
                        "request (docs/ENERGY.md)")
    g.add_argument("--profiles-file", type=ca.PathArg("in-file", what="a TOML file of energy profiles"), metavar="TOML", default=None,
                   help="user energy profiles (schemas/energy-profiles.schema.json), used with --profile")
    g.add_argument("--dvs", action="store_true",
                   help="with --profile: local runs at the lowest DVS clock that meets the deadline")
    if not leader:
        g.add_argument("--mode", choices=("best", "thesis"), default="best", help="pipeline mode (default best)")
        g.add_argument("--process", default=None, metavar="MODULE:FUNC",
                       help="process function for local execution (default: the drivable pipeline)")
    g.add_argument("--wait-ms", type=ca.non_negative("milliseconds", hi=3600000, example="2000"), default=2000.0, metavar="MS",
                   help="before the first frame, wait up to MS for a cloud or leader to appear (default 2000)")
    g.add_argument("--seed", type=ca.count("seed", lo=0, hi=2**32 - 1, example="7"), default=None, help="seed of synthetic frames (default: from the id)")
    g.add_argument("--start-file", type=ca.PathArg("out-file", example="runs/x/ready/fleet.ready"), metavar="PATH", default=None,
                   help="once connected and warmed up, wait until PATH exists (a launcher writes it, holding "
                        "the run's time 0 in unix ns, when the whole fleet is up), then start at a phase of its "
                        "own within one frame period (from --id and --seed), as independent robots would, and "
                        "send until time 0 + --duration; 'scmr up' and 'scmr demo' pass RUN/ready/fleet.ready, "
                        "'scmr scenario run' OUT/ready/run.start.  With no such file it waits (and says so)")
    g.add_argument("--drain-s", type=ca.non_negative("seconds", hi=3600, example="5"), default=5.0, metavar="S",
                   help="drain phase: after the last frame, keep sending queued telemetry for up to S seconds "
                        "while a tier can take it (default 5); what is left stays queued on disk and is sent at "
                        "the next start (reported as queued, not lost)")
    g.add_argument("--telemetry-memory-bytes", type=ca.count("bytes", lo=0, hi=1 << 40, example="4194304"),
                   default=MEMORY_BUFFER_BYTES, metavar="N",
                   help="telemetry records the disk queue refuses (full disk, I/O error, queue full) are kept in "
                        f"memory up to N bytes (default {MEMORY_BUFFER_BYTES}, about 14,000 records) and sent from "
                        "there while a cloud stores them; beyond it they are dropped and counted; 0: no buffer")
    g.add_argument("--keep-masks", type=ca.count("masks", lo=1, hi=10**9, example="1000"), default=DEFAULT_KEEP_MASKS,
                   metavar="N", help=f"keep only the newest N masks in OUT/inbox (default {DEFAULT_KEEP_MASKS}); "
                                     "older ones are deleted as new ones arrive, so a long run's folder stays bounded")
    g.add_argument("--keep-all", action="store_true",
                   help="keep every mask in OUT/inbox (no retention; the folder grows with the run)")
    g.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    from scmr_mesh.viz import (
        add_rerun_peer_args,  # light: rerun itself is imported only with a flag
    )

    add_rerun_peer_args(p)


def _setup_logging(args) -> None:
    path = getattr(args, "log_file", None)
    root = logging.getLogger()
    if path:
        try:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            handler = logging.FileHandler(path, encoding="utf-8")
        except OSError as exc:
            raise InputError(f"--log-file {path}: cannot open ({exc})") from None
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        for h in list(root.handlers):
            if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler):
                root.removeHandler(h)
        root.addHandler(handler)
    # peers log their life cycle at INFO by default (scmr -v raises the rest)
    logging.getLogger("scmr_mesh").setLevel(min(logging.INFO, root.level or logging.INFO))


def require_security(args, command: str) -> None:
    """Refuse to start a peer without a security profile unless ``--insecure`` says so (one line)."""
    if getattr(args, "security", None) and getattr(args, "insecure", False):
        raise InputError(f"scmr {command}: give either --security PROFILE or --insecure, not both")
    if not getattr(args, "security", None) and not getattr(args, "insecure", False):
        raise InputError(
            f"scmr {command} will not join an unauthenticated mesh: give --security peers/secure/mtls.toml "
            "--credentials DIR (make DIR with `scmr certs --out DIR --peers cloud,leader,robot1,...`), or "
            "--insecure to run without authentication (anyone who reaches the port can join)")


def fleet_policy(args):
    """The fleet (``fleet.json``: roles, lead grants, priority caps) of the peer's security profile, or None."""
    if not getattr(args, "security", None):
        return None
    from scmr_mesh.security.credentials import load_fleet
    from scmr_mesh.security.profile import load_profile

    profile = load_profile(args.security, credentials=getattr(args, "credentials", None))
    if profile.credentials is None:
        return None
    return load_fleet(profile.credentials)


def check_grant(args, command: str, name: str, *, tier: str | None = None, lead: bool = False) -> None:
    """Refuse at start a peer whose identity the fleet's policy does not let do its job (one line).

    Without it the peer would start and every honest peer would silently drop what it serves.
    """
    fleet = fleet_policy(args)
    if fleet is None:
        return
    peer = fleet.get(name)
    if tier is not None and not peer.may_serve(tier):
        raise InputError(f"scmr {command}: identity {name!r} has role {peer.role!r} in {fleet.directory}/fleet.json "
                         f"and may not serve the {tier} tier; make its certificate with {name}={tier} "
                         "(`scmr certs --peers ...`)")
    if lead and not peer.leads:
        raise InputError(f"scmr {command}: identity {name!r} is not leader-capable in {fleet.directory}/fleet.json; "
                         f"make its certificate with {name}=robot+leader-capable (`scmr certs --peers ...`) or drop "
                         "--leader-capable")


def _policy_setup(args):
    """Service setup hook: cap each robot's priority at the fleet's grant (no-op without a profile)."""
    fleet = fleet_policy(args)
    if fleet is None:
        return None

    def setup(svc) -> None:
        svc.priority_cap = fleet.priority_cap

    return setup


def _mesh(args, mode: str = "peer"):
    from scmr_mesh.mesh.config import MAX_MESSAGE_BYTES, from_args

    mesh = from_args(args, mode=mode)
    limit = getattr(args, "max_request_bytes", None)
    if limit:  # the transport must let the largest admitted request through (docs/ZENOH.md section 9)
        mesh.max_message_bytes = max(MAX_MESSAGE_BYTES, int(limit) + (8 << 20))
    return mesh


def _cmd_cloud(args) -> int:
    from scmr_mesh.mesh.peers import run_service

    require_security(args, "cloud")
    check_grant(args, "cloud", args.node, tier="cloud")
    _setup_logging(args)
    return run_service(args.node, _mesh(args), tier="cloud", workers=args.workers, process=args.process,
                       max_request_bytes=args.max_request_bytes, ready_file=args.ready_file,
                       setup=_setup(args, "cloud"), verbose=bool(args.verbose), budget_ms=args.budget_ms)


def _cmd_leader(args) -> int:
    require_security(args, "leader")
    check_grant(args, "leader", args.node, lead=True)
    _setup_logging(args)
    body = None
    if args.images or args.synthetic or args.bag:
        if not args.out:
            raise InputError("the leader acts as a robot only with --out DIR; add --out")
        args.id = args.node
        args.mode = args.mode or "best"
        _check_robot_args(args)

        def body(session, stop, r2r, ready):
            return _robot_body(args, session, stop, r2r, ready=ready)

    rc = _run_candidate(args, args.node, capability_default="leader", workers=args.workers, body=body)
    _raise_problem(args)
    return rc


def _cmd_robot(args) -> int:
    from scmr_mesh.mesh.config import close_session, open_session
    from scmr_mesh.mesh.peers import StopFlag, clear_ready

    require_security(args, "robot")
    check_grant(args, "robot", args.id, lead=bool(args.leader_capable))
    _setup_logging(args)
    _check_robot_args(args)
    if args.leader_capable:
        if args.workers is not None and args.workers < 1:
            raise InputError(f"--workers must be >= 1, got {args.workers}")

        def body(session, stop, r2r, ready):
            return _robot_body(args, session, stop, r2r, ready=ready)

        rc = _run_candidate(args, args.id, capability_default=None, workers=args.workers, body=body)
        _raise_problem(args)
        return rc
    stop = StopFlag().install()
    clear_ready(args.ready_file)
    session = open_session(_mesh(args))
    try:
        rc = _robot_body(args, session, stop.event)
    finally:
        close_session(session)
        clear_ready(args.ready_file)
        stop.restore()
    _raise_problem(args)
    return rc


def _hedge_ms(text: str):
    """``--hedge-ms``: ``auto``, ``off`` or a number of milliseconds (> 0, at most an hour)."""
    t = str(text).strip().lower()
    if t in ("auto", "off"):
        return t
    try:
        v = float(t)
    except ValueError:
        raise ValueError("not auto, off or a number of milliseconds") from None
    if v > 3600000:
        raise ValueError("more than an hour (3600000 ms)")
    return v


def _check_robot_args(args):
    """Validate the robot flags before anything starts; return the frame source."""
    from scmr_mesh.mesh.robot import frames_from_args, pick_seed

    if args.rate is not None and args.rate <= 0:
        raise InputError(f"--rate must be > 0, got {args.rate}")
    if args.deadline_ms <= 0:
        raise InputError(f"--deadline-ms must be > 0, got {args.deadline_ms}")
    if args.count is not None and args.count < 0:
        raise InputError(f"--count must be >= 0, got {args.count}")
    if args.duration is not None and args.duration < 0:
        raise InputError(f"--duration must be >= 0, got {args.duration}")
    args._frames = frames_from_args(args.images, args.synthetic,
                                    seed=args.seed if args.seed is not None else pick_seed(args.id),
                                    jpeg_quality=args.jpeg_quality, bag=getattr(args, "bag", None),
                                    topic=getattr(args, "topic", None))
    return args._frames


def _robot_body(args, session, stop: threading.Event, r2r=None, ready=None) -> int:
    from scmr_mesh.mesh.peers import write_ready
    from scmr_mesh.mesh.robot import Robot

    entered_ns = time.time_ns()
    duration = args.duration
    frames = getattr(args, "_frames", None) or _check_robot_args(args)
    opts = _robot_options(args)
    profile = _energy_profile(args)
    robot = Robot(args.id, args.out, options=opts)
    fleet = fleet_policy(args)
    if fleet is not None:  # route to, and accept replies from, only nodes the fleet lets serve each tier
        robot.view.trust = fleet.may_serve
    placer = _energy_placer(args, robot, profile)
    agent = None
    telemetry = None
    rerun_viz = None
    recorder = None
    try:
        recorder = _mcap_recorder(args, robot)
        rerun_viz = _robot_viz(args, robot)
        robot.attach(session)
        if r2r is not None:  # the election ranks this candidate by its own battery
            r2r.battery = robot.battery
        agent = _data_agent(robot, args)
        if opts.local_fallback:
            robot.warm_local()
        if args.wait_ms > 0 and not robot.view.wait_for_tier(args.wait_ms / 1e3):
            log.warning("robot %s: no cloud or leader visible after %.0f ms; starting anyway", args.id, args.wait_ms)
        robot.prepare()
        # ready once it could send at once: a launcher's time 0 (--start-file) finds it warmed up
        if ready is not None:  # a candidate: its ready file says what it serves, written now
            ready()
        elif getattr(args, "ready_file", None):
            write_ready(args.ready_file, {"role": "robot", "node": args.id, "zid": str(session.info.zid()),
                                          "keys": [], "candidate": r2r is not None,
                                          "leading": r2r is not None and r2r.role == "leader"})
        if getattr(args, "start_file", None):
            start_ns = _wait_for_start(args, stop)
            if start_ns is None:
                frames = iter(())  # stopped while waiting: no frames, a normal exit
            else:
                duration = send_window(args.duration, start_ns, entered_ns, time.time_ns())
        info = session.info
        log.info("robot %s zenoh links: peers=%s routers=%s", args.id,
                 sorted(str(z) for z in info.peers_zid()), sorted(str(z) for z in info.routers_zid()))
        last = [0.0]

        def progress(rec):
            if args.quiet:
                return
            now = time.monotonic()
            if now - last[0] >= 2.0:
                last[0] = now
                s = robot.stats
                print(f"robot {args.id}: {s['requests']} requests, {s['succeeded']} ok, by tier {s['by_tier']}, "
                      + (f"{s['mismatched']} MISMATCHED replies (not used), " if s["mismatched"] else "")
                      + f"last ToR {rec['tor_ms']:.1f} ms via {rec['tier']}", file=sys.stderr, flush=True)

        stats = robot.run(frames, rate_hz=args.rate, count=args.count, duration_s=duration, stop=stop,
                          progress=progress)
    finally:
        if agent is not None:  # drain, write OUT/telemetry.json, keep the rest queued on disk
            telemetry = agent.close(drain_s=args.drain_s, summary_path=Path(args.out) / "telemetry.json")
        robot.close()
        if rerun_viz is not None:
            rerun_viz.close()
        if recorder is not None:
            recorder.close()
    extra = {"energy": placer.summary()} if placer is not None else {}
    if recorder is not None:
        extra["mcap"] = {"path": str(recorder.path), "messages": recorder.messages}
    if telemetry is not None:
        extra["telemetry"] = {k: telemetry[k] for k in ("sent", "queued", "refused", "dropped", "lost")}
    if robot.telemetry_errors:
        extra["telemetry_errors"] = robot.telemetry_errors
    if robot.mismatched:
        extra["mismatched_by_node"] = dict(robot.mismatched)
    emit_json_line({"robot": args.id, **stats, **extra})
    # raised by the command once the session is closed, so it is the last line on stderr
    args._problem = _robot_problem(args.id, telemetry, robot.telemetry_errors, robot.mismatched)
    return 0


def _robot_options(args):
    """The :class:`RobotOptions` of the robot flags (``scmr robot``, ``scmr leader``, ``scmr ros``)."""
    from scmr_mesh.mesh.robot import RobotOptions
    from scmr_mesh.mesh.work import DEFAULT_PROCESS

    hedge = getattr(args, "hedge_ms", "auto")
    return RobotOptions(deadline_ms=args.deadline_ms, redundant=args.redundant, local_fallback=args.local_fallback,
                        priority=args.priority, mode=args.mode or "best",
                        process=getattr(args, "process", None) or DEFAULT_PROCESS,
                        hedge=hedge != "off", hedge_ms=hedge if isinstance(hedge, float) else None,
                        keep_masks=None if getattr(args, "keep_all", False)
                        else getattr(args, "keep_masks", DEFAULT_KEEP_MASKS))


def _cmd_ros(args) -> int:
    """``scmr ros``: the robot session on the mesh, a client session of the ROS router, the bridge between."""
    from scmr_mesh.keys import check_name
    from scmr_mesh.mesh.config import close_session, open_session
    from scmr_mesh.mesh.peers import StopFlag, clear_ready, write_ready
    from scmr_mesh.mesh.robot import Robot
    from scmr_mesh.mesh.ros import RosBridge, ros_mode_for, ros_node_name, ros_session_config
    from scmr_mesh.ros import wire as rw

    require_security(args, "ros")
    check_name(args.id, what="--id")
    check_grant(args, "ros", args.id)
    rw.check_topic(args.image_topic, flag="--image-topic")
    rw.check_topic(args.mask_topic, flag="--mask-topic")
    if args.mask_topic == args.image_topic:
        raise InputError(f"--mask-topic {args.mask_topic} is the --image-topic; give another topic for the masks")
    node = args.node_name or ros_node_name(args.id)
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", node):
        raise InputError(f"--node-name {node!r} is not a ROS node name: letters, digits and _, not starting with a digit")
    ros_connect = args.ros_connect or ["tcp/localhost:7447"]
    for ep in ros_connect:
        if not re.fullmatch(r"[a-z0-9]+/[^\s/]\S*", ep):
            raise InputError(f"--ros-connect {ep!r} is not a zenoh endpoint: give PROTO/ADDRESS such as "
                             "tcp/localhost:7447 (where rmw_zenohd listens)")
    ros_mc = ros_session_config(ros_connect, args.ros_cfg, mode=ros_mode_for(args.ros_mode, ros_connect),
                                shm=args.ros_shm)
    ros_mc.build()  # a bad --ros-connect / --ros-cfg is one line before anything starts
    _setup_logging(args)
    stop = StopFlag().install()
    clear_ready(args.ready_file)
    session = open_session(_mesh(args))
    robot = bridge = ros_session = recorder = agent = None
    stats = telemetry = None
    try:
        robot = Robot(args.id, args.out, options=_robot_options(args))
        recorder = _mcap_recorder(args, robot)
        fleet = fleet_policy(args)
        if fleet is not None:
            robot.view.trust = fleet.may_serve
        robot.attach(session)
        agent = _data_agent(robot, args)  # telemetry queued on disk until a tier stores it, as scmr robot
        if args.local_fallback:
            robot.warm_local()
        if args.wait_ms > 0 and not robot.view.wait_for_tier(args.wait_ms / 1e3):
            log.warning("ros %s: no cloud or leader visible after %.0f ms; starting anyway", args.id, args.wait_ms)
        robot.prepare()
        try:
            ros_session = open_session(ros_mc)
        except MeshError:
            raise MeshError(f"scmr ros: no Zenoh router answers at --ros-connect {' '.join(ros_connect)}; start "
                            "rmw_zenohd on the ROS host (`ros2 run rmw_zenoh_cpp rmw_zenohd`) or give its "
                            "endpoint") from None
        bridge = RosBridge(robot, ros_session, domain=args.domain, image_topic=args.image_topic,
                           mask_topic=args.mask_topic, compressed=args.compressed, rate_hz=args.rate,
                           jpeg_quality=args.jpeg_quality, node_name=node, full_frames=args.full_frames)
        bridge.start()
        write_ready(args.ready_file, {"role": "ros", "node": args.id, "zid": str(session.info.zid()),
                                      "ros_zid": str(ros_session.info.zid()), "ros_mode": ros_mc.mode, "ros_node": node,
                                      "keys": []})
        if not args.quiet:
            print(f"ros {args.id}: serving {args.image_topic} (domain {args.domain}, joined as a {ros_mc.mode} of "
                  f"{' '.join(ros_connect)}) -> {args.mask_topic}",
                  file=sys.stderr, flush=True)
        last = [0.0]

        def progress(rec):
            now = time.monotonic()
            if not args.quiet and now - last[0] >= 2.0:
                last[0] = now
                st = bridge.stats
                print(f"ros {args.id}: {st.received} received, {st.served} served, {st.dropped} dropped, "
                      f"{sum(st.rejected.values())} rejected, last ToR {rec['tor_ms']:.1f} ms via {rec['tier']}",
                      file=sys.stderr, flush=True)

        stats = bridge.run(stop.event, count=args.count, progress=progress)
    finally:
        if bridge is not None:
            bridge.close()
        if agent is not None:
            telemetry = agent.close(summary_path=Path(args.out) / "telemetry.json")
        if robot is not None:
            robot.close()
        if recorder is not None:
            recorder.close()
        if ros_session is not None:
            close_session(ros_session)
        close_session(session)
        clear_ready(args.ready_file)
        stop.restore()
    summary = {"robot": args.id, **robot.stats, "ros": stats.as_dict()}
    if robot.mismatched:
        summary["mismatched_by_node"] = dict(robot.mismatched)
    if recorder is not None:
        summary["mcap"] = {"path": str(recorder.path), "messages": recorder.messages}
    if telemetry is not None:
        summary["telemetry"] = {k: telemetry[k] for k in ("sent", "queued", "refused", "lost")}
    emit_json_line(summary)
    problems = []
    lost = _robot_problem(args.id, telemetry, robot.telemetry_errors, robot.mismatched)
    if lost:
        problems.append(lost.split(": ", 1)[1])
    if stats.rejected:
        problems.append(f"{sum(stats.rejected.values())} sample(s) rejected "
                        + ", ".join(f"{k}={v}" for k, v in sorted(stats.rejected.items())))
    if stats.failed or stats.publish_errors:
        problems.append(f"{stats.failed} frame(s) got no mask, {stats.publish_errors} mask or overlay publish error(s)")
    if problems:
        raise MeshError(f"ros {args.id}: " + "; ".join(problems) + " (see the log)")
    return 0


def _mcap_recorder(args, robot):
    """``--mcap FILE``: a :class:`~scmr_mesh.ros.record.McapRecorder` observing ``robot`` (None without the flag)."""
    if not getattr(args, "mcap", None):
        return None
    from scmr_mesh.ros.record import McapRecorder

    rec = McapRecorder(args.mcap, robot.id, jpeg_quality=getattr(args, "jpeg_quality", 90))
    robot.add_observer(rec.observe)
    return rec


def _wait_for_start(args, stop: threading.Event) -> int | None:
    """Wait for ``--start-file``, then for this robot's phase.

    Returns the run's time 0 written in the file (unix ns; 0 when it holds
    none), or None when stopped first.
    """
    import random

    path = Path(args.start_file)
    if not path.exists():
        log.info("robot %s: ready; waiting for %s to start", args.id, path)
        if not args.quiet:
            print(f"robot {args.id}: ready; waiting for {path} to start", file=sys.stderr, flush=True)
        while not path.exists():
            if stop.wait(0.01):
                return None
    try:
        t0_ns = int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        t0_ns = 0
    phase = random.Random(f"phase:{args.id}:{args.seed}").uniform(0.0, 1.0 / args.rate)
    return None if stop.wait(phase) else t0_ns


def send_window(duration_s: float | None, start_ns: int, entered_ns: int, now_ns: int) -> float | None:
    """How long a robot gated by ``--start-file`` still sends: up to time 0 + ``duration_s``.

    Only for a robot that was up before time 0 (``entered_ns < start_ns``); one
    started later (a robot restarted during a scenario, told the time left)
    keeps its ``duration_s``.  ``start_ns`` 0 (no time in the file) keeps it too.

    >>> send_window(10.0, start_ns=5_000_000_000, entered_ns=1, now_ns=5_300_000_000)
    9.7
    >>> send_window(10.0, start_ns=5_000_000_000, entered_ns=6_000_000_000, now_ns=6_100_000_000)
    10.0
    >>> send_window(None, start_ns=5, entered_ns=1, now_ns=6) is None
    True
    """
    if duration_s is None or start_ns <= 0 or entered_ns >= start_ns:
        return duration_s
    return max(0.0, duration_s - (now_ns - start_ns) / 1e9)


def emit_json_line(obj, stream=None) -> None:
    """Write ``obj`` as one JSON line in a single write.

    Peers run unbuffered (``PYTHONUNBUFFERED``) with stderr on the same log file:
    ``print`` writes the text and the newline separately, and a log line from
    another thread landed between them, so the summary line did not parse.
    """
    stream = stream or sys.stdout
    stream.write(json.dumps(obj) + "\n")
    stream.flush()


def _raise_problem(args) -> None:
    """Exit 1 with one line when the robot's telemetry was lost or a reply was mismatched (:func:`_robot_problem`)."""
    problem = getattr(args, "_problem", None)
    if problem:
        raise MeshError(problem)


def _robot_problem(rid: str, telemetry: dict | None, errors: int,
                   mismatched: dict[str, int] | None = None) -> str | None:
    """What makes a robot exit 1: telemetry lost or not produced, replies that did not answer
    the request they came for (``Robot.mismatched``: a lying or broken server); None when none."""
    problems = []
    if mismatched:
        n = sum(mismatched.values())
        problems.append(f"{n} repl{'y' if n == 1 else 'ies'} did not answer the request they came for (robot, seq "
                        "or frame digest not the request's; never used): "
                        + ", ".join(f"{k} {v}" for k, v in sorted(mismatched.items())))
    if telemetry is not None and telemetry["lost"]:
        refused = ",".join(telemetry["refused_seqs"])
        mem = telemetry.get("memory") or {}
        why = []
        if telemetry.get("dropped"):
            why.append(f"{telemetry['dropped']} dropped with the memory buffer full")
        if mem.get("unsent"):
            why.append(f"{mem['unsent']} still in memory at exit")
        problems.append(f"{telemetry['lost']} of {telemetry['sent']} telemetry records lost"
                        + (f" (refused by the disk: seqs {refused}: {telemetry['error']}"
                           + (f"; {', '.join(why)}" if why else "") + ")" if refused else "")
                        + "; see OUT/telemetry.json")
    if errors:
        problems.append(f"{errors} telemetry message(s) could not be produced (see the log)")
    if not problems:
        return None
    return f"robot {rid}: " + "; ".join(problems)


def _robot_viz(args, robot):
    """Log overlays, QoS and battery to rerun with --rerun-url/--rerun-save (or $SCMR_RERUN_*; scmr_mesh.viz)."""
    from scmr_mesh import keys
    from scmr_mesh.viz import RerunOptions, robot_viz

    rv = robot_viz(RerunOptions.for_peer(args, robot.id), robot.id)
    if rv is not None:
        robot.add_observer(rv.observe)
        def log_and_forward(message, forward):
            rv.log_telemetry(battery=message.get("battery"))
            return forward(message)

        robot.add_telemetry_handler(log_and_forward)
        view_cb = robot.view.on_liveliness  # bound before attach() subscribes with it

        def on_liveliness(sample):
            view_cb(sample)
            try:
                _, role, node = keys.parse(str(sample.key_expr))
                rv.log_liveliness(role, node, appeared(sample))
            except Exception as exc:  # the viewer never breaks routing
                log.debug("rerun liveliness log failed: %s", exc)

        robot.view.on_liveliness = on_liveliness
    return rv


def _energy_profile(args):
    """The --profile energy profile (validated before anything starts), or None."""
    if not getattr(args, "profile", None):
        if getattr(args, "profiles_file", None) or getattr(args, "dvs", False):
            raise InputError("--profiles-file and --dvs only apply with --profile NAME; add --profile")
        return None
    from scmr_mesh.energy import get_profile

    return get_profile(args.profile, profiles_file=args.profiles_file)


def _energy_placer(args, robot, profile):
    """Install the energy policy as the robot's placement and record annotator."""
    if profile is None:
        return None
    from scmr_mesh.energy.live import EnergyPlacer

    placer = EnergyPlacer(profile, robot_id=robot.id, deadline_s=robot.options.deadline_ms / 1e3, dvs=args.dvs)
    robot.placement = placer
    robot.annotators.append(placer.annotate)
    return placer


def _data_args(p: argparse.ArgumentParser, role: str) -> None:
    """The data tier's flags (ODS, sync period, telemetry queue): scmr_mesh.mesh.data_service."""
    from scmr_mesh.mesh.data_service import add_arguments

    add_arguments(p, role)


def _setup(args, tier: str):
    """Service setup hooks: the data tier, then the priority negotiator (--queue)."""
    from scmr_mesh.mesh import negotiation

    return negotiation.chain(_policy_setup(args), _data_setup(args, tier), negotiation.service_setup(args))


def _data_setup(args, tier: str):
    """Service setup hook installing the data tier (telemetry store, data buffer, leader sync)."""
    from scmr_mesh.mesh.data_service import service_setup

    return service_setup(args, tier)


def _data_agent(robot, args):
    """Queue the robot's telemetry on disk until a tier stores it (data_service.TelemetryAgent)."""
    from scmr_mesh.mesh.data_service import attach_robot

    agent = attach_robot(robot, args)
    if agent is not None:  # records the disk refuses wait in memory up to this bound (docs/DATA.md)
        agent.memory_bytes = int(getattr(args, "telemetry_memory_bytes", agent.memory_bytes))
        stale_telemetry_summary(getattr(args, "out", None))
    return agent


def stale_telemetry_summary(out) -> None:
    """Remove ``OUT/telemetry.json`` left by an earlier life of this robot (written at a clean exit).

    The run's telemetry count reads it to learn whether a leader may still hold records the robot
    relayed (``settle_telemetry``); a summary from before a restart would say "none" for a robot
    killed since.  While the robot runs there is no summary: "may hold".
    """
    if out:
        try:
            (Path(out) / "telemetry.json").unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("cannot remove the stale %s (%s): the run's telemetry count may stop waiting early",
                        Path(out) / "telemetry.json", exc)


def _cmd_router(args) -> int:
    from scmr_mesh.mesh.peers import run_router

    require_security(args, "router")
    _setup_logging(args)
    return run_router(_mesh(args, mode="router"), ready_file=args.ready_file)


def parse_swarm_members(plans: Sequence[Sequence[str]]) -> list[argparse.Namespace]:
    """Each member's arguments parsed and checked as ``scmr robot`` would, before anything starts."""
    import contextlib
    import io

    parser = ca.ScmrArgumentParser(prog="scmr robot")
    _robot_command_args(parser)
    members, seen = [], set()
    for i, argv in enumerate(plans):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                args = parser.parse_args(list(argv))
        except SystemExit:
            last = (err.getvalue().strip().splitlines() or ["invalid arguments"])[-1]
            for prefix in ("scmr robot: ", "scmr: ", "error: "):
                last = last.removeprefix(prefix)
            raise InputError(f"swarm member {i + 1}: {last}") from None
        if args.id in seen:
            raise InputError(f"swarm member {i + 1}: robot id {args.id!r} twice; give each member its own --id")
        seen.add(args.id)
        if args.leader_capable:
            raise InputError(f"swarm member {args.id}: --leader-capable robots run as their own process "
                             "(scmr robot --leader-capable), not in a swarm")
        if not args.out:
            raise InputError(f"swarm member {args.id}: --out DIR is required (its records and masks)")
        try:
            require_security(args, "robot")
            check_grant(args, "robot", args.id)
            _check_robot_args(args)
        except ScmrError as exc:
            raise InputError(f"swarm member {args.id}: {exc}") from None
        members.append(args)
    return members


def _cmd_swarm(args) -> int:
    from scmr_mesh.mesh.config import close_session, open_session
    from scmr_mesh.mesh.peers import StopFlag, clear_ready, write_ready

    from scmr_mesh.mesh.swarm import read_plan

    members = parse_swarm_members(read_plan(args.plan))
    stop = StopFlag().install()
    clear_ready(args.ready_file)
    for m in members:
        clear_ready(m.ready_file)
    sessions: list[Any] = []
    results: dict[str, Any] = {}
    threads: list[threading.Thread] = []
    try:
        for m in members:  # every identity opens its own session: its own certificate and links
            sessions.append(open_session(_mesh(m)))

        def play(m, session) -> None:
            try:
                results[m.id] = _robot_body(m, session, stop.event)
            except Exception as exc:  # one member's failure is reported, the others go on
                log.exception("swarm member %s failed", m.id)
                results[m.id] = exc
                _swarm_member_failed(m, exc)

        for m, s in zip(members, sessions):
            t = threading.Thread(target=play, args=(m, s), name=f"robot-{m.id}", daemon=True)
            t.start()
            threads.append(t)
        ready_files = [Path(m.ready_file) for m in members if m.ready_file]
        while not stop.event.is_set() and any(t.is_alive() for t in threads):
            if ready_files and all(f.exists() for f in ready_files):
                write_ready(args.ready_file, {"role": "swarm", "robots": [m.id for m in members]})
                ready_files = []
            for t in threads:
                t.join(0.05)
        # stopped: every member's run loop sees the same stop event and ends its frame
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    finally:
        for s in sessions:
            close_session(s)
        clear_ready(args.ready_file)
        for m in members:
            clear_ready(m.ready_file)
        stop.restore()
    problems = [getattr(m, "_problem", None) for m in members]
    problems = [p for p in problems if p]
    if problems:
        raise MeshError(f"{len(problems)} of {len(members)} swarm robots failed: " + "; ".join(problems))
    return 0


def _swarm_member_failed(m: argparse.Namespace, exc: Exception) -> None:
    """Mark member ``m`` failed with ``exc`` (one line; the swarm exits 1)."""
    m._problem = f"robot {m.id}: {type(exc).__name__}: {exc}"
    print(f"scmr: error: {m._problem}", file=sys.stderr, flush=True)


def _cmd_tap(args) -> int:
    from scmr_mesh.mesh.config import close_session, from_args, open_session
    from scmr_mesh.mesh.peers import StopFlag
    from scmr_mesh.mesh.tap import OPEN_CFG, run_tap

    require_security(args, "tap")
    try:
        import zenoh

        zenoh.KeyExpr(args.keyexpr)
    except Exception as exc:
        raise InputError(f"scmr tap: {args.keyexpr!r} is not a zenoh key expression ({str(exc).split(' at /')[0]}); "
                         "example: 'scmr/load/**'") from None
    stop = StopFlag().install()
    mesh = from_args(args)
    mesh.cfg = [OPEN_CFG, *mesh.cfg]  # a --cfg of the operator's still wins
    session = open_session(mesh)
    try:
        n = run_tap(session, args.keyexpr, get=args.get, count=args.count, duration_s=args.duration,
                    stop=stop.event)
    finally:
        close_session(session)
    if args.count is not None and n < args.count and stop.signal is None:
        print(f"scmr tap: {n} of {args.count} messages on {args.keyexpr} in {args.duration:g} s", file=sys.stderr)
        return 1
    return 0

