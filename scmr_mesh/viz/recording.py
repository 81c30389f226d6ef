"""The rerun viewer: red/green overlays and QoS time lines of a fleet run.

This is the only module of scmr-mesh that imports ``rerun``, and it does so
inside functions: a command run without rerun flags never imports rerun and
never starts or writes anything rerun-related.

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

import argparse
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scmr_mesh import keys
from scmr_mesh.errors import InputError, ScmrError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

log = logging.getLogger(__name__)

#: Application id shared by every process of a fleet run.
APP_ID = "scmr-mesh"
#: Default viewer port (the one rerun's own examples use).
DEFAULT_PORT = 9876
#: Default web-viewer port of ``--serve``.
DEFAULT_WEB_PORT = 9090
#: ``--connect`` without a URL connects here.
DEFAULT_CONNECT_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"
#: Class ids of the drivability map, with label and RGBA colour.
CLASSES: tuple[tuple[int, str, tuple[int, int, int, int]], ...] = (
    (1, "drivable", (0, 200, 0, 255)),
    (2, "non-drivable", (220, 0, 0, 255)),
)
#: Serving tier drawn as a level in the tier plot (``failed`` = no answer).
TIER_LEVEL: dict[str | None, int] = {"cloud": 2, "leader": 1, "local": 0, None: -1, "failed": -1}
#: Annotation-context root: everything under it shares the class colours.
ROBOT_ROOT = f"{keys.ROOT}/robot"
FAULTS = f"{keys.ROOT}/faults"
FLEET = f"{keys.ROOT}/fleet"

#: Environment fallback for peers started by a runner that cannot pass flags
#: (``scmr scenario run``): the sink URL, or a folder for one ``<peer>.rrd``
#: each (peers in network namespaces cannot reach the host's loopback), and
#: the shared recording id.
ENV_URL, ENV_SAVE_DIR, ENV_RECORDING_ID = "SCMR_RERUN_URL", "SCMR_RERUN_SAVE_DIR", "SCMR_RERUN_RECORDING_ID"

_URL_RE = re.compile(r"^(rerun|rerun\+http|rerun\+https)://[^/\s]+/proxy$")


class ViewerError(ScmrError):
    """The rerun viewer or sink could not be started, reached or read."""


# --------------------------------------------------------------------------
# analytics off, rerun executable


def state_dir() -> Path:
    """Folder that holds the rerun config/data dirs of project processes.

    ``$SCMR_RERUN_HOME`` if set (tests point it to a temporary folder), else
    ``$XDG_CACHE_HOME/scmr-mesh/rerun`` (``~/.cache/scmr-mesh/rerun``).
    """
    env = os.environ.get("SCMR_RERUN_HOME")
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "scmr-mesh" / "rerun"


def rerun_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for a rerun child process with usage analytics off.

    rerun reads ``<config dir>/rerun/analytics.json`` (``analytics_enabled``)
    from the XDG config dir; this points ``XDG_CONFIG_HOME`` and
    ``XDG_DATA_HOME`` into :func:`state_dir`, where that file says ``false``
    (what ``rerun analytics disable`` would write), so no analytics are
    collected and the user's own rerun dirs are neither read nor written.

    Parameters
    ----------
    base : mapping, optional
        Environment to start from (default ``os.environ``).

    Returns
    -------
    dict
        A new environment.
    """
    env = dict(os.environ if base is None else base)
    root = state_dir()
    config_home, data_home = root / "config", root / "data"
    cfg = config_home / "rerun" / "analytics.json"
    want = {
        "analytics_enabled": False,
        "analytics_id": "scmr-mesh-analytics-disabled",
        "metadata": {},
        "config_file_path": str(cfg),
        "data_dir_path": str(data_home / "rerun" / "analytics"),
    }
    try:
        current = json.loads(cfg.read_text()) if cfg.is_file() else None
    except (OSError, ValueError):
        current = None
    if current != want:
        cfg.parent.mkdir(parents=True, exist_ok=True)
        tmp = cfg.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(want))
        os.replace(tmp, cfg)
    data_home.mkdir(parents=True, exist_ok=True)
    env["XDG_CONFIG_HOME"] = str(config_home)
    env["XDG_DATA_HOME"] = str(data_home)
    return env


def rerun_executable() -> str:
    """Path of the ``rerun`` CLI that comes with rerun-sdk.

    ``$RERUN_CLI_PATH`` if set, else the binary inside the ``rerun_cli``
    package, else ``rerun`` on ``PATH``.

    Raises
    ------
    ViewerError
        When no rerun executable is found.
    """
    env = os.environ.get("RERUN_CLI_PATH")
    if env:
        return env
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        exe = Path(spec.origin).parent / "rerun"
        if exe.is_file():
            return str(exe)
    found = shutil.which("rerun")
    if found:
        return found
    raise ViewerError(
        "the rerun executable was not found (looked in the rerun_cli package and on PATH); "
        "reinstall with `pip install rerun-sdk==0.41.0` or set RERUN_CLI_PATH"
    )


def run_rerun_cli(args: Sequence[str], *, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """Run ``rerun ARGS`` with analytics off and return the finished process.

    Parameters
    ----------
    args : sequence of str
        Arguments after ``rerun`` (e.g. ``["rrd", "verify", "f.rrd"]``).
    timeout : float
        Seconds before giving up.

    Raises
    ------
    ViewerError
        When the CLI cannot be run or times out (a non-zero exit is returned,
        not raised).
    """
    cmd = [rerun_executable(), *map(str, args)]
    try:
        return subprocess.run(
            cmd, env=rerun_env(), capture_output=True, text=True, timeout=timeout, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ViewerError(f"`{' '.join(cmd)}` failed: {exc}") from exc


# --------------------------------------------------------------------------
# flags


def add_rerun_args(parser: argparse.ArgumentParser) -> None:
    """Add the rerun flags users know from rerun's examples to a fleet command.

    ``--save FILE.rrd``, ``--spawn``, ``--serve`` and ``--connect [URL]`` are
    mutually exclusive; ``--rerun-recording-id`` picks the recording id.
    Without any of them nothing rerun-related happens.
    """
    group = parser.add_argument_group(
        "rerun viewer",
        "Watch red/green overlays and QoS plots (one recording for the whole fleet). "
        "Without these flags nothing rerun-related runs.",
    )
    mx = group.add_mutually_exclusive_group()
    mx.add_argument("--save", metavar="FILE.rrd", help="save the recording to FILE.rrd (open it with `scmr view FILE.rrd`)")
    mx.add_argument("--spawn", action="store_true", help="start a native rerun viewer and stream to it")
    mx.add_argument(
        "--serve",
        action="store_true",
        help=f"serve a web viewer on http://127.0.0.1:{DEFAULT_WEB_PORT} (gRPC on {DEFAULT_PORT})",
    )
    mx.add_argument(
        "--connect",
        nargs="?",
        const=DEFAULT_CONNECT_URL,
        metavar="URL",
        help=f"stream to a running viewer (default {DEFAULT_CONNECT_URL}; a port number also works)",
    )
    group.add_argument(
        "--rerun-recording-id",
        metavar="ID",
        help="recording id (default: a fresh one); runs with the same id merge in the viewer",
    )


def add_rerun_peer_args(parser: argparse.ArgumentParser) -> None:
    """Add the rerun flags of a peer process (robot, cloud, leader).

    A fleet process passes ``--rerun-url URL --rerun-recording-id ID``
    (:meth:`FleetViz.child_args`); a peer started by hand can also use
    ``--rerun-save FILE.rrd``.  These names do not clash with Zenoh's
    ``--connect``/``--listen``.
    """
    group = parser.add_argument_group("rerun viewer (set by the fleet command)")
    mx = group.add_mutually_exclusive_group()
    mx.add_argument("--rerun-url", metavar="URL", help="log into the rerun sink at URL (rerun+http://HOST:PORT/proxy)")
    mx.add_argument("--rerun-save", metavar="FILE.rrd", help="log into FILE.rrd")
    group.add_argument("--rerun-recording-id", metavar="ID", help="shared recording id of the fleet run")


def normalize_url(url: str | int) -> str:
    """Turn a port or viewer URL into a ``rerun+http://HOST:PORT/proxy`` URL.

    Raises
    ------
    InputError
        When ``url`` is neither a port nor a rerun gRPC URL.
    """
    text = str(url).strip()
    if text.isdigit():
        port = int(text)
        if not 0 < port < 65536:
            raise InputError(f"--connect port must be 1-65535, got {text}")
        return f"rerun+http://127.0.0.1:{port}/proxy"
    if not _URL_RE.match(text):
        raise InputError(
            f"--connect expects a port or a URL like {DEFAULT_CONNECT_URL}, got {text!r}"
        )
    return text


def check_reachable(url: str, *, timeout: float = 1.0) -> str:
    """Return ``url`` if something listens at its host and port, else raise.

    rerun's ``connect_grpc`` blocks about 5 s on an unreachable URL and then
    drops the data, so every stream checks first.

    Raises
    ------
    ViewerError
        When nothing accepts a TCP connection at the URL's host and port.
    """
    m = re.match(r"^[a-z+]+://(\[[^\]]+\]|[^:/]+)(?::(\d+))?/", url)
    if not m:
        raise InputError(f"not a rerun gRPC URL: {url!r} (expected {DEFAULT_CONNECT_URL})")
    host = m.group(1).strip("[]")
    port = int(m.group(2) or (443 if url.startswith("rerun+https") else 80))
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return url
    except OSError as exc:
        raise ViewerError(
            f"no rerun viewer listens at {url} ({exc.strerror or exc}); start one with "
            "`rerun` (or use --spawn / --serve / --save instead of --connect)"
        ) from exc


@dataclass(frozen=True)
class RerunOptions:
    """Where a process sends its rerun data (parsed rerun flags).

    Attributes
    ----------
    mode : str
        ``"save"``, ``"spawn"``, ``"serve"`` or ``"connect"``.
    target : str or None
        The ``.rrd`` path (save) or the gRPC URL (connect).
    recording_id : str or None
        Shared recording id; ``None`` lets :class:`FleetViz` pick one.
    """

    mode: str
    target: str | None = None
    recording_id: str | None = None

    MODES = ("save", "spawn", "serve", "connect")

    def __post_init__(self) -> None:
        if self.mode not in self.MODES:
            raise InputError(f"rerun mode must be one of {self.MODES}, got {self.mode!r}")
        if self.mode == "save":
            if not self.target:
                raise InputError("--save needs a file name such as run.rrd")
            if not str(self.target).endswith(".rrd"):
                raise InputError(f"--save expects a FILE.rrd, got {self.target!r}; add the .rrd suffix")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RerunOptions | None:
        """Options from parsed flags, or ``None`` when no rerun flag was given.

        Understands both :func:`add_rerun_args` and :func:`add_rerun_peer_args`.
        """
        rid = getattr(args, "rerun_recording_id", None)
        if getattr(args, "rerun_url", None):
            return cls("connect", normalize_url(args.rerun_url), rid)
        if getattr(args, "rerun_save", None):
            return cls("save", args.rerun_save, rid)
        if getattr(args, "save", None):
            return cls("save", args.save, rid)
        if getattr(args, "spawn", False) is True:
            return cls("spawn", None, rid)
        if getattr(args, "serve", False) is True:
            return cls("serve", None, rid)
        connect = getattr(args, "connect", None)
        if isinstance(connect, str) and connect:
            return cls("connect", normalize_url(connect), rid)
        return None

    @classmethod
    def for_peer(cls, args: argparse.Namespace, name: str) -> RerunOptions | None:
        """A peer's options: its flags, else ``$SCMR_RERUN_URL`` / ``$SCMR_RERUN_SAVE_DIR``.

        With ``SCMR_RERUN_SAVE_DIR=DIR`` the peer saves ``DIR/<name>.rrd``.
        ``None`` when neither flags nor environment ask for rerun.
        """
        opts = cls.from_args(args)
        if opts is not None:
            return opts
        rid = os.environ.get(ENV_RECORDING_ID) or None
        if os.environ.get(ENV_URL):
            return cls("connect", normalize_url(os.environ[ENV_URL]), rid)
        if os.environ.get(ENV_SAVE_DIR):
            # one file per process: a restarted peer must not overwrite its first life
            out = Path(os.environ[ENV_SAVE_DIR]) / f"{keys.check_name(name)}-{os.getpid()}.rrd"
            return cls("save", str(out), rid)
        return None


# --------------------------------------------------------------------------
# sinks (fleet process)


def entity_name(text: str) -> str:
    """``text`` as one entity-path/key chunk: runs of other characters become ``_``.

    >>> entity_name("cloud | leader,robot1")
    'cloud_leader_robot1'
    """
    name = re.sub(r"[^A-Za-z0-9_.\-]+", "_", text).strip("_")[:64]
    return name or "_"


def has_display() -> bool:
    """Whether a native viewer window can open (always true off Linux)."""
    import sys

    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _port_open(port: int, host: str = "127.0.0.1") -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _wait_port(proc: subprocess.Popen, port: int, *, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if _port_open(port):
            return
        if proc.poll() is not None:
            err = (proc.stderr.read() if proc.stderr else b"").decode(errors="replace")
            tail = " | ".join(err.strip().splitlines()[-3:]) or "no output"
            raise ViewerError(f"{what} exited with status {proc.returncode} before listening on port {port}: {tail}")
        time.sleep(0.05)
    _stop(proc)
    raise ViewerError(f"{what} did not listen on port {port} within {timeout:.0f} s; is the port taken?")


def _stop(proc: subprocess.Popen, *, grace: float = 5.0) -> int | None:
    """SIGINT (rerun finishes its file), then SIGTERM, then SIGKILL, to its process group.

    Every rerun process here is started in its own session, so the group is
    exactly that process and whatever it started.
    """
    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        except PermissionError:
            proc.send_signal(sig)
        try:
            return proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()


class _Sink:
    """The one gRPC endpoint every process of a run logs into."""

    def __init__(self, options: RerunOptions, *, port: int | None = None, web_port: int | None = None) -> None:
        self.options = options
        self.proc: subprocess.Popen | None = None
        self.raw_path: Path | None = None
        self.web_url: str | None = None
        self.hint = ""
        mode = options.mode
        if mode == "connect":
            self.url = normalize_url(options.target or DEFAULT_CONNECT_URL)
            self.hint = f"streaming to the rerun viewer at {self.url}"
            return
        exe = rerun_executable()
        if mode == "save":
            out = Path(options.target).expanduser()
            if not out.parent.exists():
                raise InputError(f"--save {options.target}: folder {out.parent} does not exist; create it first")
            self.out_path = out
            self.raw_path = out.with_name(out.name + ".partial")
            port = port or _free_port()
            cmd = [exe, "--save", str(self.raw_path), "--port", str(port), "--bind", "127.0.0.1"]
            detach = False
            what = "the rerun recorder (`rerun --save`)"
        elif mode == "spawn":
            port = port or DEFAULT_PORT
            if not _port_open(port) and not has_display():
                raise ViewerError(
                    "--spawn needs a display for the native viewer (DISPLAY/WAYLAND_DISPLAY unset); "
                    "use --serve for the web viewer or --save FILE.rrd"
                )
            if _port_open(port):
                self.url = f"rerun+http://127.0.0.1:{port}/proxy"
                self.hint = f"a rerun viewer already listens on port {port}: streaming to it"
                return
            cmd = [exe, "--port", str(port), "--expect-data-soon", "--memory-limit", "75%"]
            detach = True
            what = "the rerun viewer (`rerun --port`)"
        else:  # serve
            port = port or DEFAULT_PORT
            web_port = web_port or DEFAULT_WEB_PORT
            cmd = [exe, "--serve-web", "--port", str(port), "--web-viewer-port", str(web_port), "--bind", "127.0.0.1"]
            detach = False
            what = "the rerun web viewer (`rerun --serve-web`)"
        log.info("starting %s: %s", what, " ".join(cmd))
        try:
            self.proc = subprocess.Popen(
                cmd,
                env=rerun_env(),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE if not detach else subprocess.DEVNULL,
                start_new_session=True,  # Ctrl-C in the fleet does not reach it; we stop it ourselves
            )
        except OSError as exc:
            raise ViewerError(f"could not start {what}: {exc}") from exc
        _wait_port(self.proc, port, timeout=15.0, what=what)
        if self.proc.stderr is not None:  # keep the pipe from filling up
            threading.Thread(target=_drain, args=(self.proc.stderr,), daemon=True).start()
        self.url = f"rerun+http://127.0.0.1:{port}/proxy"
        if mode == "save":
            self.hint = f"recording to {self.out_path} (open it with `scmr view {self.out_path}`)"
        elif mode == "spawn":
            self.hint = f"rerun viewer started on port {port}"
        else:
            self.web_url = f"http://127.0.0.1:{web_port}/?url={self.url}"
            self.hint = f"rerun web viewer: {self.web_url}"

    def close(self, *, extra: Sequence[Path] = ()) -> Path | None:
        """Stop the sink; for ``--save`` finalise the file (merging ``extra`` in) and return its path."""
        mode = self.options.mode
        if self.proc is None or mode == "spawn":
            return None  # a spawned viewer stays open for the user
        if mode == "save" and self.raw_path is not None:
            _wait_quiet(self.raw_path)  # the recorder may still be writing what peers sent last
        _stop(self.proc)
        if mode != "save":
            return None
        raw, out = self.raw_path, self.out_path
        if raw is None or not raw.exists():
            raise ViewerError(f"the rerun recorder wrote nothing to {raw}; no recording saved")
        res = run_rerun_cli(["rrd", "merge", str(raw), *map(str, extra), "-o", str(out)])
        if res.returncode != 0 or not out.exists():
            raw.replace(out)  # unfinalised but loadable
            log.warning("rerun rrd merge failed (%s); kept the raw stream as %s", res.stderr.strip()[-200:], out)
        else:
            raw.unlink(missing_ok=True)
        return out


def _wait_quiet(path: Path, *, quiet: float = 0.3, limit: float = 3.0) -> None:
    """Wait until ``path`` has not grown for ``quiet`` s (at most ``limit`` s)."""
    deadline = time.monotonic() + limit
    last, since = -1, time.monotonic()
    while time.monotonic() < deadline:
        size = path.stat().st_size if path.exists() else -1
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since >= quiet:
            return
        time.sleep(0.05)


def _merge(paths: Sequence[Path], out: Path) -> Path | None:
    """``rerun rrd merge PATHS -o OUT``; ``None`` (and a warning) when it fails."""
    res = run_rerun_cli(["rrd", "merge", *map(str, paths), "-o", str(out)])
    if res.returncode != 0 or not out.exists():
        log.warning("rerun rrd merge of %d files failed: %s", len(paths), res.stderr.strip()[-200:])
        return None
    return out


def _drain(stream) -> None:
    try:
        for _ in iter(lambda: stream.read(65536), b""):
            pass
    except (OSError, ValueError):
        pass


# --------------------------------------------------------------------------
# loggers


def _mask_to_classes(mask: np.ndarray) -> np.ndarray:
    """Class-id image (1 drivable, 2 non-drivable) from a mask.

    Accepts an ``(H, W)`` bool/integer mask (non-zero = drivable) or an
    ``(H, W, 3)`` uint8 red/green map (green channel above red = drivable).
    """
    import numpy as np

    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] in (3, 4):
        drivable = m[..., 1].astype(np.int16) > m[..., 0].astype(np.int16)
    elif m.ndim == 2:
        drivable = m != 0
    else:
        raise InputError(f"mask must be (H, W) or (H, W, 3), got shape {m.shape}")
    return np.where(drivable, 1, 2).astype(np.uint8)


def _rgb(image: np.ndarray, shape: tuple[int, int] | None) -> np.ndarray:
    import numpy as np

    a = np.asarray(image)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise InputError(f"camera frame must be (H, W, 3) RGB, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    if shape is not None and a.shape[:2] != shape:
        import cv2

        a = cv2.resize(a, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(a)


class _Stream:
    """One process's handle on the shared recording (imports rerun)."""

    def __init__(self, options: RerunOptions, *, recording_id: str | None = None, url: str | None = None) -> None:
        import rerun as rr  # the only place rerun is imported

        self.rr = rr
        self.recording_id = recording_id or options.recording_id or uuid.uuid4().hex
        self.rec = rr.RecordingStream(APP_ID, recording_id=self.recording_id)
        if url is not None:
            self.rec.connect_grpc(check_reachable(url))
        elif options.mode == "save":
            out = Path(options.target).expanduser()
            if not out.parent.exists():
                raise InputError(f"--rerun-save {options.target}: folder {out.parent} does not exist")
            self.rec.save(str(out))
        elif options.mode == "connect":
            self.rec.connect_grpc(check_reachable(normalize_url(options.target or DEFAULT_CONNECT_URL)))
        else:
            raise InputError(
                f"a peer logs with --rerun-url or --rerun-save, not {options.mode!r}; "
                "start the fleet command with --spawn/--serve instead"
            )
        self._lock = threading.Lock()
        self.rec.log(
            ROBOT_ROOT,
            rr.AnnotationContext([(i, label, color) for i, label, color in CLASSES]),
            static=True,
        )

    def at(self, t_unix_ns: int | None, seq: int | None = None) -> None:
        """Set the time lines for the next log calls (``request`` only when given)."""
        import numpy as np

        t = time.time_ns() if t_unix_ns is None else int(t_unix_ns)
        self.rec.set_time("wall_time", timestamp=np.datetime64(t, "ns"))
        if seq is None:
            self.rec.disable_timeline("request")
        else:
            self.rec.set_time("request", sequence=int(seq))

    def close(self, timeout: float = 5.0) -> None:
        try:
            self.rec.flush(timeout_sec=timeout)
        except RuntimeError as exc:  # sink unreachable: drop the rest, never hang
            log.warning("rerun: could not flush the recording (%s); some data is lost", exc)
        try:
            self.rec.disconnect()
        except RuntimeError as exc:
            log.warning("rerun: disconnect failed: %s", exc)


class _Viz:
    """Shared fleet-level logging (liveliness, faults, text)."""

    _stream: _Stream
    _alive: dict[str, bool]
    _faults: dict[tuple, set]
    _last_alive: dict[tuple[str, str], bool]

    def _step_series(self, entity: str, name: str) -> None:
        """Declare ``entity`` a step-shaped series (once per process)."""
        s = self._stream
        if entity not in self._alive:
            s.rec.log(
                entity,
                s.rr.SeriesLines(names=name, interpolation_mode="StepAfter", aggregation_policy="Off"),
                static=True,
            )
            self._alive[entity] = True

    def log_alive(self, role: str, node: str, alive: bool, *, t_unix_ns: int | None = None) -> None:
        """Log that ``node`` (cloud, leader or robot) is alive (1) or gone (0), as a step."""
        s = self._stream
        key = keys.alive(role, node)
        with s._lock:
            self._step_series(key, f"{node} alive")
            s.at(t_unix_ns)
            s.rec.log(key, s.rr.Scalars(1.0 if alive else 0.0))

    def log_fault(self, fault: Mapping[str, Any]) -> None:
        """Log a scenario fault as a step (1 while on) and start/end markers.

        ``fault`` is a :mod:`scmr_mesh.metrics` fault dict: ``kind``,
        ``target``, ``start_unix_ns`` and optionally ``end_unix_ns``.  Calling
        it again for the same fault (same target and start) logs only what is
        new, so a runner can call it when the fault starts and again when it
        ends.
        """
        s, rr = self._stream, self._stream.rr
        target = entity_name(str(fault.get("target") or "fleet"))
        kind = str(fault.get("kind", "fault"))
        entity = f"{FAULTS}/{target}"
        ident = (target, fault.get("start_unix_ns"))
        done = self._faults.setdefault(ident, set())
        with s._lock:
            self._step_series(entity, f"fault: {kind} {target}")
            if "start" not in done:
                done.add("start")
                start = time.time_ns() if fault.get("start_unix_ns") is None else int(fault["start_unix_ns"])
                s.at(start - 1_000_000)  # 0 just before: the step up shows
                s.rec.log(entity, rr.Scalars(0.0))
                s.at(start)
                s.rec.log(entity, rr.Scalars(1.0))
                s.rec.log(f"{FAULTS}/log", rr.TextLog(f"{kind} {target} starts", level="WARN"))
            if fault.get("end_unix_ns") is not None and "end" not in done:
                done.add("end")
                s.at(fault["end_unix_ns"])
                s.rec.log(entity, rr.Scalars(0.0))
                s.rec.log(f"{FAULTS}/log", rr.TextLog(f"{kind} {target} ends", level="INFO"))

    def update(
        self,
        *,
        alive: Mapping[tuple[str, str], bool] | None = None,
        records: Sequence[Mapping[str, Any]] = (),
        faults: Sequence[Mapping[str, Any]] = (),
        t_unix_ns: int | None = None,
    ) -> None:
        """One call per supervisor tick: log alive *changes*, new records, faults.

        Parameters
        ----------
        alive : mapping, optional
            ``{(role, node): is_alive}``; only changes since the last call are logged.
        records : sequence of mapping
            Records finished since the last call (for the fleet RoR).
        faults : sequence of mapping
            All faults so far (see :meth:`log_fault`; repeated calls log only news).
        """
        try:
            for (role, node), up in (alive or {}).items():
                if self._last_alive.get((role, node)) != bool(up):
                    self._last_alive[(role, node)] = bool(up)
                    self.log_alive(role, node, bool(up), t_unix_ns=t_unix_ns)
            for rec in records:
                if hasattr(self, "log_record"):
                    self.log_record(rec)
            for fault in faults:
                self.log_fault(fault)
        except Exception as exc:  # the viewer must never stop a run
            log.warning("rerun: could not log fleet state: %s: %s", type(exc).__name__, exc)

    def log_text(self, entity: str, text: str, *, level: str = "INFO", t_unix_ns: int | None = None) -> None:
        """Log one line of text at ``entity``."""
        s = self._stream
        with s._lock:
            s.at(t_unix_ns)
            s.rec.log(entity, s.rr.TextLog(text, level=level))

    def close(self) -> None:
        self._stream.close()


class RobotViz(_Viz):
    """Logs one robot's frames, overlays and QoS into the shared recording.

    Parameters
    ----------
    options : RerunOptions
        From :meth:`RerunOptions.from_args` (peer flags).
    robot : str
        Robot id (one key chunk).
    image_every : int
        Log the camera frame and map for every ``image_every``-th request (the
        scalars are logged for every request).
    jpeg_quality : int
        JPEG quality of the camera frame (the map is lossless).

    Examples
    --------
    >>> viz = RobotViz(RerunOptions("save", "r0.rrd"), "r0")  # doctest: +SKIP
    >>> robot.add_observer(viz.observe)                        # doctest: +SKIP
    """

    def __init__(self, options: RerunOptions, robot: str, *, image_every: int = 1, jpeg_quality: int = 80) -> None:
        self.robot = keys.check_name(robot, what="robot id")
        if image_every < 1:
            raise InputError(f"image_every must be >= 1, got {image_every}")
        self.image_every = int(image_every)
        self.jpeg_quality = int(jpeg_quality)
        self._stream = _Stream(options)
        self._alive, self._faults, self._last_alive = {}, {}, {}
        self._n = 0
        self._ok = 0
        self.camera = f"{ROBOT_ROOT}/{self.robot}/camera"
        self.results = f"{keys.RESULTS}/{self.robot}"
        self.telemetry = f"{keys.TELEMETRY}/{self.robot}"
        rr, rec = self._stream.rr, self._stream.rec
        rec.log(f"{self.results}/tor_ms", rr.SeriesLines(names=f"{self.robot} ToR (ms)"), static=True)
        rec.log(f"{self.results}/tier", rr.SeriesPoints(names=f"{self.robot} tier"), static=True)
        rec.log(f"{self.results}/ror", rr.SeriesLines(names=f"{self.robot} RoR"), static=True)

    def observe(self, record: Mapping[str, Any], rgb: np.ndarray | None = None, mask: np.ndarray | None = None, *, srm: np.ndarray | None = None) -> None:
        """Log one finished request (usable as ``robot.add_observer(viz.observe)``).

        Parameters
        ----------
        record : mapping
            The request record (``seq``, ``ok``, ``tier``, ``tor_ms``,
            ``sent_unix_ns``, ``received_unix_ns``, ``served_by``, ``error``,
            optionally ``energy_j`` and ``battery``).
        rgb : (H, W, 3) uint8 array, optional
            The camera frame; resized to the map's shape.
        mask : (h, w) bool/int or (h, w, 3) uint8 array, optional
            The drivability map (non-zero or green = drivable).
        srm : (h, w, 3) uint8 array, optional
            The SRM image.
        """
        s, rr = self._stream, self._stream.rr
        seq = record.get("seq")
        t = record.get("received_unix_ns") or record.get("sent_unix_ns")
        ok = bool(record.get("ok"))
        tier = record.get("tier") if ok else None
        with s._lock:
            self._n += 1
            self._ok += ok
            s.at(t, seq)
            rec = s.rec
            if ok and record.get("tor_ms") is not None:
                rec.log(f"{self.results}/tor_ms", rr.Scalars(float(record["tor_ms"])))
            rec.log(f"{self.results}/tier", rr.Scalars(float(TIER_LEVEL.get(tier, -1))))
            rec.log(f"{self.results}/ror", rr.Scalars(self._ok / self._n))
            line = (
                f"#{seq} {tier} by {record.get('served_by')} in {float(record.get('tor_ms') or 0):.1f} ms"
                if ok
                else f"#{seq} failed: {record.get('error')}"
            )
            rec.log(f"{self.results}/log", rr.TextLog(line, level="INFO" if ok else "WARN"))
            if record.get("energy_j") is not None:
                rec.log(f"{self.telemetry}/energy_j", rr.Scalars(float(record["energy_j"])))
            if record.get("battery") is not None:
                rec.log(f"{self.telemetry}/battery", rr.Scalars(float(record["battery"])))
            if (self._n - 1) % self.image_every == 0:
                self._log_images(rgb, mask, srm)

    def _log_images(self, rgb, mask, srm) -> None:
        s, rr = self._stream, self._stream.rr
        shape = None
        if mask is not None:
            classes = _mask_to_classes(mask)
            shape = classes.shape
        if rgb is not None:
            import cv2

            frame = _rgb(rgb, shape)
            ok, jpg = cv2.imencode(".jpg", frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if ok:
                s.rec.log(self.camera, rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
        if mask is not None:
            s.rec.log(f"{self.camera}/drivable", rr.SegmentationImage(classes, opacity=0.5))
        if srm is not None:
            import cv2

            ok, jpg = cv2.imencode(".jpg", _rgb(srm, None)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
            if ok:
                s.rec.log(f"{ROBOT_ROOT}/{self.robot}/srm", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))

    def log_liveliness(self, role: str, node: str, alive: bool, *, t_unix_ns: int | None = None) -> None:
        """Log what this robot's liveliness subscriber saw (cloud and leader tokens only).

        Entity ``scmr/alive/<role>/<node>/<robot>``: 1 while the token is up, as
        a step series, so each robot's view of each serving node is one line
        ("cloud0 seen by r1").
        """
        if role not in ("cloud", "leader"):
            return
        s = self._stream
        entity = f"{keys.alive(role, entity_name(node))}/{self.robot}"
        with s._lock:
            self._step_series(entity, f"{node} seen by {self.robot}")
            s.at(t_unix_ns)
            s.rec.log(entity, s.rr.Scalars(1.0 if alive else 0.0))

    def log_telemetry(self, *, battery: float | None = None, energy_j: float | None = None, t_unix_ns: int | None = None) -> None:
        """Log battery level and/or energy outside a request."""
        s, rr = self._stream, self._stream.rr
        with s._lock:
            s.at(t_unix_ns)
            if battery is not None:
                s.rec.log(f"{self.telemetry}/battery", rr.Scalars(float(battery)))
            if energy_j is not None:
                s.rec.log(f"{self.telemetry}/energy_j", rr.Scalars(float(energy_j)))


class FleetViz(_Viz):
    """The fleet process's side: opens the sink, fans it out, logs fleet state.

    Parameters
    ----------
    options : RerunOptions
        From :meth:`RerunOptions.from_args` (fleet flags).
    robots : sequence of str
        Robot ids, for the blueprint (a grid of their overlays).
    port, web_port : int, optional
        Ports of a started sink (defaults: a free port for ``--save``, 9876
        and 9090 otherwise).

    Examples
    --------
    >>> fv = FleetViz(opts, robots=["r0", "r1"])          # doctest: +SKIP
    >>> cmd = ["scmr", "robot", "r0", *fv.child_args()]   # doctest: +SKIP
    >>> fv.log_alive("cloud", "cloud0", True)             # doctest: +SKIP
    >>> fv.close()                                        # doctest: +SKIP
    """

    def __init__(self, options: RerunOptions, *, robots: Sequence[str] = (), port: int | None = None, web_port: int | None = None) -> None:
        self.options = options
        self.recording_id = options.recording_id or uuid.uuid4().hex
        self._sink = _Sink(options, port=port, web_port=web_port)
        try:
            if options.mode == "save":
                # the fleet's own data goes straight to a file (complete once flushed), merged at close;
                # the recorder serves the peers only
                self._own_file = self._sink.out_path.with_name(self._sink.out_path.stem + ".fleet.partial.rrd")
                own = RerunOptions("save", str(self._own_file), self.recording_id)
                self._stream = _Stream(own, recording_id=self.recording_id)
            else:
                self._own_file = None
                self._stream = _Stream(options, recording_id=self.recording_id, url=self._sink.url)
        except BaseException:
            self._sink.close()
            raise
        self.robots = [keys.check_name(r, what="robot id") for r in robots]
        self._alive, self._faults, self._last_alive = {}, {}, {}
        self._n = 0
        self._ok = 0
        rr = self._stream.rr
        self._stream.rec.log(f"{FLEET}/ror", rr.SeriesLines(names="fleet RoR"), static=True)
        self.send_blueprint(self.robots)
        self.saved_path: Path | None = None
        self.peers_path: Path | None = None
        self._extra_files: list[Path] = []

    @property
    def url(self) -> str:
        """gRPC URL of the sink (what children connect to)."""
        return self._sink.url

    @property
    def hint(self) -> str:
        """One line for the user: where the recording goes and how to open it."""
        return self._sink.hint

    def child_args(self) -> list[str]:
        """Arguments to append to a peer's command line (see :func:`add_rerun_peer_args`)."""
        return ["--rerun-url", self.url, "--rerun-recording-id", self.recording_id]

    def child_env(self, *, save_dir: str | os.PathLike | None = None) -> dict[str, str]:
        """Environment for peers that take no rerun flags (see :meth:`RerunOptions.for_peer`).

        Parameters
        ----------
        save_dir : path-like, optional
            Make each peer save ``save_dir/<peer>.rrd`` instead of connecting to
            the sink (for peers in network namespaces, which cannot reach the
            host's loopback); pass the files to :meth:`add_files` afterwards.
        """
        env = {ENV_RECORDING_ID: self.recording_id}
        if save_dir is not None:
            Path(save_dir).mkdir(parents=True, exist_ok=True)
            env[ENV_SAVE_DIR] = str(save_dir)
        else:
            env[ENV_URL] = self.url
        return env

    def add_files(self, paths: Sequence[str | os.PathLike]) -> None:
        """Recordings written by peers on their own (``child_env(save_dir=...)``).

        With ``--save`` they are merged into the saved file at :meth:`close`;
        with a live viewer they are merged into ``<first file's folder>/peers.rrd``
        (open it with ``scmr view``): they cannot be replayed into the live sink
        in order.
        """
        self._extra_files.extend(Path(p) for p in paths if Path(p).is_file())

    def send_blueprint(self, robots: Sequence[str]) -> None:
        """Lay out the viewer: robot overlays in a grid, ToR and tier plots below."""
        import rerun.blueprint as rrb

        robots = list(robots)
        overlays = [rrb.Spatial2DView(origin=f"{ROBOT_ROOT}/{r}/camera", name=r) for r in robots]
        if not overlays:
            overlays = [rrb.Spatial2DView(origin=ROBOT_ROOT, name="robots")]
        def per_robot(leaf: str) -> list[str]:
            if robots:
                return [f"{keys.RESULTS}/{r}/{leaf}" for r in robots]
            return [f"{keys.RESULTS}/**"]

        unit = rrb.ScalarAxis(range=(-0.1, 1.1))
        plots = rrb.Horizontal(
            rrb.TimeSeriesView(origin=keys.RESULTS, contents=per_robot("tor_ms"), name="ToR (ms)"),
            rrb.TimeSeriesView(
                origin=keys.RESULTS,
                contents=per_robot("tier"),
                name="tier (2 cloud, 1 leader, 0 local, -1 failed)",
                axis_y=rrb.ScalarAxis(range=(-1.3, 2.3)),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=keys.ALIVE, name="alive (1 up, 0 gone)", axis_y=unit),
                rrb.TimeSeriesView(origin=FAULTS, name="faults (1 while on)", axis_y=unit),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    origin=keys.ROOT, contents=[f"{FLEET}/ror", *per_robot("ror")], name="RoR so far", axis_y=unit
                ),
                rrb.TextLogView(origin=keys.ROOT, name="events"),
            ),
            column_shares=[3, 3, 2, 2],
        )
        bp = rrb.Blueprint(
            rrb.Vertical(rrb.Grid(*overlays), plots, row_shares=[3, 2]),
            rrb.TimePanel(timeline="wall_time"),
            collapse_panels=False,
        )
        self._stream.rec.send_blueprint(bp, make_active=True, make_default=True)

    def log_record(self, record: Mapping[str, Any]) -> None:
        """Count one finished request of any robot and log the fleet RoR so far."""
        s = self._stream
        with s._lock:
            self._n += 1
            self._ok += bool(record.get("ok"))
            s.at(record.get("received_unix_ns") or record.get("sent_unix_ns"))
            s.rec.log(f"{FLEET}/ror", s.rr.Scalars(self._ok / self._n))

    def close(self) -> Path | None:
        """Flush, stop the sink and (``--save``) finalise the file; returns its path.

        Call it after the peers have exited, so their data is in.
        """
        try:
            self._stream.close()
        finally:
            own = [self._own_file] if self._own_file is not None and self._own_file.exists() else []
            self.saved_path = self._sink.close(extra=[*own, *self._extra_files])
            for f in own:
                f.unlink(missing_ok=True)
        if self._sink.options.mode != "save" and self._extra_files:
            self.peers_path = _merge(self._extra_files, self._extra_files[0].parent / "peers.rrd")
        return self.saved_path

    def __enter__(self) -> FleetViz:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def peers_env_session(
    options: RerunOptions | None, *, robots: Sequence[str] = (), save_dir: str | os.PathLike | None = None
):
    """A :class:`FleetViz` whose sink reaches peers through the environment.

    For runners that start peers without rerun flags (``scmr scenario run``):
    sets ``$SCMR_RERUN_*`` (:meth:`FleetViz.child_env`) in this process for the
    duration, so every child inherits it, then restores it, adds the peers'
    own files (``save_dir``) and closes.  Yields ``None`` when ``options`` is
    ``None`` (then nothing happens).

    Parameters
    ----------
    save_dir : path-like, optional
        Peers save ``save_dir/<peer>-<pid>.rrd`` instead of connecting (use it
        when they run in network namespaces).
    """
    if options is None:
        yield None
        return
    fv = FleetViz(options, robots=robots)
    env = fv.child_env(save_dir=save_dir)
    before = {k: os.environ.get(k) for k in (ENV_URL, ENV_SAVE_DIR, ENV_RECORDING_ID)}
    os.environ.update(env)
    try:
        yield fv
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        if save_dir is not None:
            fv.add_files(sorted(Path(save_dir).glob("*.rrd")))
        fv.close()


def robot_viz(options: RerunOptions | None, robot: str, **kw: Any) -> RobotViz | None:
    """A :class:`RobotViz` for ``robot``, or ``None`` when ``options`` is ``None``."""
    return None if options is None else RobotViz(options, robot, **kw)


def fleet_viz(options: RerunOptions | None, *, robots: Sequence[str] = (), **kw: Any) -> FleetViz | None:
    """A started :class:`FleetViz`, or ``None`` when ``options`` is ``None``."""
    return None if options is None else FleetViz(options, robots=robots, **kw)


# --------------------------------------------------------------------------
# reading recordings back


_CHUNK_RE = re.compile(r"^Chunk\(\S+\) with (\d+) rows .*? - (/\S*) - data columns: \[(.*)\]$")


def check_rrd(path: str | os.PathLike) -> Path:
    """Return ``path`` if it looks like a rerun recording, else raise.

    Raises
    ------
    InputError
        When the file is missing, empty or does not start with rerun's magic.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"recording {str(path)!r} not found; pass a .rrd file written with --save")
    with p.open("rb") as f:
        head = f.read(4)
    if head[:3] != b"RRF":
        raise InputError(f"{str(path)!r} is not a rerun recording (starts with {head!r}, expected b'RRF2')")
    return p


def rrd_rows(path: str | os.PathLike) -> dict[str, dict[str, int]]:
    """Rows per entity and component of a ``.rrd``, read with ``rerun rrd print``.

    Returns
    -------
    dict
        ``{entity_path: {component: rows}}`` of the recording (not the
        blueprint), e.g. ``{"/scmr/results/r0/tor_ms": {"Scalars:scalars": 20}}``.

    Raises
    ------
    InputError, ViewerError
        For a missing/invalid file, or when the CLI fails.
    """
    p = check_rrd(path)
    res = run_rerun_cli(["rrd", "print", str(p)])
    if res.returncode != 0:
        raise ViewerError(f"`rerun rrd print {p}` failed: {res.stderr.strip()[-300:]}")
    out: dict[str, dict[str, int]] = {}
    in_recording = False
    for line in res.stdout.splitlines():
        if "StoreId(" in line or line.strip().startswith("Recording,") or line.strip().startswith("Blueprint,"):
            if line.strip().startswith("Recording,"):
                in_recording = True
            elif line.strip().startswith("Blueprint,"):
                in_recording = False
            continue
        m = _CHUNK_RE.match(line.strip())
        if not m or not in_recording:
            continue
        rows, entity, cols = int(m.group(1)), m.group(2), m.group(3)
        comps = out.setdefault(entity, {})
        for col in cols.split():
            comp = col.split("@", 1)[-1]
            comps[comp] = comps.get(comp, 0) + rows
    return out


# --------------------------------------------------------------------------
# looking at recordings


def _use_rerun_env_here() -> None:
    """Point this process's XDG dirs at :func:`state_dir` (for viewers rerun spawns itself)."""
    env = rerun_env()
    os.environ["XDG_CONFIG_HOME"] = env["XDG_CONFIG_HOME"]
    os.environ["XDG_DATA_HOME"] = env["XDG_DATA_HOME"]


def screenshot(
    path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    settle: float = 6.0,
    max_size: int | None = None,
    port: int | None = None,
) -> Path:
    """Render a ``.rrd`` in rerun's headless native viewer and save a PNG.

    Needs a Vulkan driver (Debian: ``apt-get install -y mesa-vulkan-drivers``,
    the lavapipe software renderer); without one the viewer panics with
    "Failed to get render context".  Meant for the CLI (``scmr view
    --screenshot``): it points this process's XDG dirs at :func:`state_dir`.

    Parameters
    ----------
    path : path-like
        The recording.
    out : path-like
        PNG to write.
    settle : float
        Seconds to wait after opening (chunks load lazily).
    max_size : int, optional
        Longest side of the PNG in pixels (default: the viewer's 1920x1080).
    port : int, optional
        Port of the headless viewer (default: a free one).

    Returns
    -------
    Path
        ``out``.
    """
    rrd = check_rrd(path)
    out = Path(out)
    if not out.parent.exists():
        raise InputError(f"--screenshot {out}: folder {out.parent} does not exist")
    _use_rerun_env_here()
    from rerun.experimental import ViewerClient

    port = port or _free_port()
    try:
        client = ViewerClient.spawn(
            headless=True, port=port, executable_path=rerun_executable(), hide_welcome_screen=True
        )
    except Exception as exc:  # the bindings raise plain exceptions
        raise ViewerError(
            f"the headless rerun viewer did not start ({exc}); it needs a Vulkan driver: "
            "apt-get install -y mesa-vulkan-drivers"
        ) from exc
    try:
        client.open(str(rrd.resolve()))
        time.sleep(settle)
        png = client.take_screenshot(max_size=max_size)
    except Exception as exc:
        raise ViewerError(
            f"the headless rerun viewer could not render {rrd} ({type(exc).__name__}: {exc}); "
            "a Vulkan driver is needed: apt-get install -y mesa-vulkan-drivers"
        ) from exc
    finally:
        for closer in ("quit", "close"):
            try:
                getattr(client, closer)()
            except Exception:  # already gone
                pass
        pid = getattr(client, "_pid", None)
        if pid:
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    out.write_bytes(png)
    return out
