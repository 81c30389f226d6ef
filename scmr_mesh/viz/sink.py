"""The sink all processes of a run log into: a headless recorder, a viewer, or a URL."""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from scmr_mesh import deathsig
from scmr_mesh.errors import InputError
from scmr_mesh.ports import free_port
from scmr_mesh.viz.common import (
    DEFAULT_CONNECT_URL,
    DEFAULT_PORT,
    DEFAULT_WEB_PORT,
    ViewerError,
)
from scmr_mesh.viz.options import RerunOptions, has_display, normalize_url
from scmr_mesh.viz.rerun_cli import rerun_env, rerun_executable, run_rerun_cli

log = logging.getLogger(__name__)

def _dies_with_us():
    """The ``preexec_fn`` of a recorder or web viewer: SIGTERM when this process dies
    (:func:`scmr_mesh.deathsig.preexec`, SIGTERM reset to its default first), or None off the main
    thread (the signal follows the forking thread, and a worker thread that ended would stop rerun).

    rerun runs in its own session, so a parent killed with SIGKILL (no handler runs) left it
    recording or serving: two web viewers of ``scmr view`` were found after a failed test.
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    return deathsig.preexec(signal.SIGTERM, reset=True)


# --------------------------------------------------------------------------
# sinks (fleet process)


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
        nice = 0
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
            port = port or free_port()
            cmd = [exe, "--save", str(self.raw_path), "--port", str(port), "--bind", "127.0.0.1"]
            detach = False
            nice = 10  # a recording must not take CPU from the requests it records
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
            for flag, p in (("web viewer", web_port), ("gRPC", port)):
                if _port_open(p):   # the wait below would take the other server for rerun
                    raise ViewerError(f"--serve: the {flag} port {p} is taken (another viewer?); stop it, "
                                      "or use --connect to stream to it")
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
                # a recorder or web viewer ends with the fleet, even a SIGKILLed one (a --save file
                # is then left as FILE.partial: rerun reads it, unfinalised); a spawned viewer stays
                # open for the user
                preexec_fn=None if detach else _dies_with_us(),
            )
        except OSError as exc:
            raise ViewerError(f"could not start {what}: {exc}") from exc
        if nice:
            try:
                os.setpriority(os.PRIO_PROCESS, self.proc.pid, nice)
            except OSError as exc:  # pragma: no cover - the recording works either way
                log.debug("could not lower the recorder's priority: %s", exc)
        _wait_port(self.proc, port, timeout=15.0, what=what)
        if mode == "serve":  # the URL printed must answer: rerun opens the web port after the gRPC one
            _wait_port(self.proc, web_port, timeout=15.0, what=what)
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


