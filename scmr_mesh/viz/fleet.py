"""The fleet process's side: :class:`FleetViz` opens the sink and logs fleet state."""

from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from scmr_mesh import keys
from scmr_mesh.viz.blueprint import fleet_blueprint
from scmr_mesh.viz.common import (
    ENV_RECORDING_ID,
    ENV_SAVE_DIR,
    ENV_URL,
    FLEET,
)
from scmr_mesh.viz.options import RerunOptions
from scmr_mesh.viz.recording import _Stream, _Viz
from scmr_mesh.viz.sink import _merge, _Sink

log = logging.getLogger(__name__)

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
        self._t_first = time.time_ns()  # the run starts: the fault plot's line starts here too
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
        """Lay out the viewer (:func:`scmr_mesh.viz.blueprint.fleet_blueprint`)."""
        self._stream.rec.send_blueprint(fleet_blueprint(robots), make_active=True, make_default=True)

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
            self._end_faults()
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


def fleet_viz(options: RerunOptions | None, *, robots: Sequence[str] = (), **kw: Any) -> FleetViz | None:
    """A started :class:`FleetViz`, or ``None`` when ``options`` is ``None``."""
    return None if options is None else FleetViz(options, robots=robots, **kw)


