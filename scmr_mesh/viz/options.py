"""Rerun flags of fleet commands and peers, and :class:`RerunOptions` (no rerun import)."""

from __future__ import annotations

import argparse
import logging
import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path

from scmr_mesh import cliargs as ca
from scmr_mesh import keys
from scmr_mesh.errors import InputError
from scmr_mesh.viz.common import (
    _URL_RE,
    DEFAULT_CONNECT_URL,
    DEFAULT_PORT,
    DEFAULT_WEB_PORT,
    ENV_RECORDING_ID,
    ENV_SAVE_DIR,
    ENV_URL,
    ViewerError,
)

log = logging.getLogger(__name__)

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
    mx.add_argument("--save", type=ca.PathArg("out-file"), metavar="FILE.rrd", help="save the recording to FILE.rrd (open it with `scmr view FILE.rrd`)")
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
    mx.add_argument("--rerun-save", type=ca.PathArg("out-file"), metavar="FILE.rrd", help="log into FILE.rrd")
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



def has_display() -> bool:
    """Whether a native viewer window can open (always true off Linux)."""
    import sys

    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


