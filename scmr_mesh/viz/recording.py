"""Per-process recording streams and the robot's logger (:class:`RobotViz`)."""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scmr_mesh import keys
from scmr_mesh.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

from scmr_mesh.viz.common import (
    APP_ID,
    CLASSES,
    DEFAULT_CONNECT_URL,
    FAULTS,
    ROBOT_ROOT,
    TIER_LEVEL,
    entity_name,
)
from scmr_mesh.viz.options import RerunOptions, check_reachable, normalize_url

log = logging.getLogger(__name__)

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
    _faults: dict[tuple, dict]
    _t_first: int | None = None
    _t_last: int | None = None
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

    def log_fault(self, fault: Mapping[str, Any], *, run_end_ns: int | None = None) -> None:
        """Log a scenario fault as a step (1 while on) and start/end markers.

        ``fault`` is a :mod:`scmr_mesh.qos.metrics` fault dict: ``kind``,
        ``target``, ``start_unix_ns`` and optionally ``end_unix_ns``.  Calling
        it again for the same fault (same target and start) logs only what is
        new, so a runner can call it when the fault starts and again when it
        ends; :meth:`close` calls it with ``run_end_ns`` (:func:`fault_points`).
        """
        s, rr = self._stream, self._stream.rr
        target = entity_name(str(fault.get("target") or "fleet"))
        kind = str(fault.get("kind", "fault"))
        entity = f"{FAULTS}/{target}"
        ident = (target, fault.get("start_unix_ns"))
        if ident not in self._faults:
            start = time.time_ns() if fault.get("start_unix_ns") is None else int(fault["start_unix_ns"])
            self._faults[ident] = {"logged": set(), "start": start, "entity": entity, "fault": dict(fault)}
        entry = self._faults[ident]
        entry["fault"].update({k: v for k, v in fault.items() if v is not None})
        end = entry["fault"].get("end_unix_ns")
        first = getattr(self, "_t_first", None)
        # the run's start only on the first fault of this entity: a later one continues its line
        fresh = not any(e["entity"] == entity and e is not entry and e["logged"] for e in self._faults.values())
        pts = fault_points(entry["start"], None if end is None else int(end),
                           run_start_ns=first if fresh else None, run_end_ns=run_end_ns)
        with s._lock:
            self._step_series(entity, f"fault: {kind} {target}")
            for t, v in pts:
                if (t, v) in entry["logged"]:
                    continue
                entry["logged"].add((t, v))
                s.at(t)
                s.rec.log(entity, rr.Scalars(v))
                if t == entry["start"] and v == 1.0:
                    s.rec.log(f"{FAULTS}/log", rr.TextLog(f"{kind} {target} starts", level="WARN"))
                elif end is not None and t == int(end) and v == 0.0:
                    s.rec.log(f"{FAULTS}/log", rr.TextLog(f"{kind} {target} ends", level="INFO"))

    def set_run_span(self, start_unix_ns: int | None, end_unix_ns: int | None) -> None:
        """Where the run starts and ends, when known (the fault lines span it; default: from this
        object's creation to :meth:`close`)."""
        if start_unix_ns is not None:
            self._t_first = int(start_unix_ns)
        if end_unix_ns is not None:
            self._t_last = int(end_unix_ns)

    def _end_faults(self) -> None:
        """At close: carry every fault's line to the end of the run (the plot's axis spans the run)."""
        now = getattr(self, "_t_last", None) or time.time_ns()
        last: dict[str, dict] = {}  # each entity's line ends with its latest fault
        for entry in self._faults.values():
            if entry["entity"] not in last or entry["start"] > last[entry["entity"]]["start"]:
                last[entry["entity"]] = entry
        try:
            for entry in last.values():
                self.log_fault(entry["fault"], run_end_ns=now)
        except Exception as exc:  # the viewer must never stop a run
            log.warning("rerun: could not close the fault plot: %s: %s", type(exc).__name__, exc)

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
        self._end_faults()
        self._stream.close()


def fault_points(start_ns: int, end_ns: int | None = None, *, run_start_ns: int | None = None,
                 run_end_ns: int | None = None) -> list[tuple[int, float]]:
    """The (time, value) points of one fault's step line (pure).

    0 just before the start (so the step up shows), 1 at the start, 0 at the end.  Each
    fault's line also runs from the run's start and to the run's end: a time-series plot fits
    its time axis to the data it holds, and with points only around the faults the faults plot
    of a 20 s run covered its 3 s of faults.

    >>> fault_points(5_000_000_000, 8_000_000_000, run_start_ns=0, run_end_ns=20_000_000_000)
    [(0, 0.0), (4999000000, 0.0), (5000000000, 1.0), (8000000000, 0.0), (20000000000, 0.0)]
    >>> fault_points(5_000_000_000, run_end_ns=20_000_000_000)[-1]  # still on at the end
    (20000000000, 1.0)
    """
    before = start_ns - 1_000_000
    pts: list[tuple[int, float]] = []
    if run_start_ns is not None and run_start_ns < before:
        pts.append((int(run_start_ns), 0.0))
    pts += [(before, 0.0), (int(start_ns), 1.0)]
    last = int(start_ns)
    if end_ns is not None:
        pts.append((int(end_ns), 0.0))
        last = max(last, int(end_ns))
    if run_end_ns is not None and run_end_ns > last:
        pts.append((int(run_end_ns), 0.0 if end_ns is not None else 1.0))
    return pts


class RobotViz(_Viz):
    """Logs one robot's frames, overlays and QoS into the shared recording.

    Nothing is logged on the caller's thread: :meth:`observe`,
    :meth:`log_liveliness` and :meth:`log_telemetry` queue what they are given
    (microseconds) and a background thread (``scmr-rerun``, at a lower CPU
    priority) logs the queue every ``batch_s`` seconds: the scalars and text
    of a batch as one column chunk per entity (``send_columns``), then its
    images (JPEG-encoded there).  So the robot's request thread never waits
    for rerun, and rerun's per-call work happens once per batch instead of
    once per request.  :meth:`flush` logs what is queued now; :meth:`close`
    flushes and closes the stream.

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
    batch_s : float
        How often the background thread logs what was queued.
    max_images : int
        Requests whose images may wait in the queue; beyond that their images
        are dropped (scalars never are) and counted in :attr:`dropped_images`.

    Examples
    --------
    >>> viz = RobotViz(RerunOptions("save", "r0.rrd"), "r0")  # doctest: +SKIP
    >>> robot.add_observer(viz.observe)                        # doctest: +SKIP
    """

    def __init__(self, options: RerunOptions, robot: str, *, image_every: int = 1, jpeg_quality: int = 80,
                 batch_s: float = 0.25, max_images: int = 64) -> None:
        self.robot = keys.check_name(robot, what="robot id")
        if image_every < 1:
            raise InputError(f"image_every must be >= 1, got {image_every}")
        if not batch_s > 0:
            raise InputError(f"batch_s must be > 0, got {batch_s}")
        self.image_every = int(image_every)
        self.jpeg_quality = int(jpeg_quality)
        self.batch_s = float(batch_s)
        self.max_images = int(max_images)
        self.dropped_images = 0
        self._stream = _Stream(options)
        self._alive, self._faults, self._last_alive = {}, {}, {}
        self._n = 0  # requests queued
        self._logged = 0  # requests logged
        self._ok = 0
        self.camera = f"{ROBOT_ROOT}/{self.robot}/camera"
        self.results = f"{keys.RESULTS}/{self.robot}"
        self.telemetry = f"{keys.TELEMETRY}/{self.robot}"
        rr, rec = self._stream.rr, self._stream.rec
        rec.log(f"{self.results}/tor_ms", rr.SeriesLines(names=f"{self.robot} ToR (ms)"), static=True)
        rec.log(f"{self.results}/tier", rr.SeriesPoints(names=f"{self.robot} tier"), static=True)
        rec.log(f"{self.results}/ror", rr.SeriesLines(names=f"{self.robot} RoR"), static=True)
        self._queue: list[tuple] = []
        self._images_waiting = 0
        self._qlock = threading.Lock()
        self._wake = threading.Event()
        self._closed = False
        self._flush_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="scmr-rerun", daemon=True)
        self._thread.start()

    # ------------------------------------------------ caller side (cheap)
    def observe(self, record: Mapping[str, Any], rgb: np.ndarray | None = None, mask: np.ndarray | None = None, *, srm: np.ndarray | None = None) -> None:
        """Queue one finished request (usable as ``robot.add_observer(viz.observe)``).

        Parameters
        ----------
        record : mapping
            The request record (``seq``, ``ok``, ``tier``, ``tor_ms``,
            ``sent_unix_ns``, ``received_unix_ns``, ``served_by``, ``error``,
            optionally ``energy_j`` and ``battery``).
        rgb : (H, W, 3) uint8 array, optional
            The camera frame; resized to the map's shape.  Kept by reference
            until logged: do not modify it afterwards.
        mask : (h, w) bool/int or (h, w, 3) uint8 array, optional
            The drivability map (non-zero or green = drivable).
        srm : (h, w, 3) uint8 array, optional
            The SRM image.
        """
        fields = {k: record.get(k) for k in ("seq", "ok", "tier", "tor_ms", "served_by", "error", "energy_j",
                                               "battery")}
        fields["t"] = record.get("received_unix_ns") or record.get("sent_unix_ns") or time.time_ns()
        with self._qlock:
            self._n += 1
            images = None
            if (self._n - 1) % self.image_every == 0 and (rgb is not None or mask is not None or srm is not None):
                if self._images_waiting < self.max_images:
                    images = (rgb, mask, srm)
                    self._images_waiting += 1
                else:
                    self.dropped_images += 1
            self._queue.append(("request", fields, images))

    def log_liveliness(self, role: str, node: str, alive: bool, *, t_unix_ns: int | None = None) -> None:
        """Queue what this robot's liveliness subscriber saw (cloud and leader tokens only).

        Entity ``scmr/alive/<role>/<node>/<robot>``: 1 while the token is up, as
        a step series, so each robot's view of each serving node is one line
        ("cloud0 seen by r1").
        """
        if role not in ("cloud", "leader"):
            return
        t = time.time_ns() if t_unix_ns is None else int(t_unix_ns)
        with self._qlock:
            self._queue.append(("alive", (role, node, bool(alive)), t))

    def log_telemetry(self, *, battery: float | None = None, energy_j: float | None = None, t_unix_ns: int | None = None) -> None:
        """Queue battery level and/or energy outside a request."""
        t = time.time_ns() if t_unix_ns is None else int(t_unix_ns)
        with self._qlock:
            self._queue.append(("telemetry", (battery, energy_j), t))

    # ------------------------------------------------ logger thread
    def _run(self) -> None:
        try:  # Linux: a nice value per thread; the robot's own threads keep theirs
            import os

            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
        except (AttributeError, OSError):
            pass
        while not self._closed:
            self._wake.wait(self.batch_s)
            self._wake.clear()
            self.flush()

    def flush(self) -> None:
        """Log everything queued so far (the background thread calls it every ``batch_s``)."""
        with self._flush_lock:
            with self._qlock:
                items, self._queue = self._queue, []
            if not items:
                return
            try:
                self._log_batch(items)
            except Exception as exc:  # the viewer must never stop a robot
                log.warning("rerun: could not log %d queued items: %s: %s", len(items), type(exc).__name__, exc)
            finally:
                with self._qlock:
                    self._images_waiting -= sum(1 for it in items if it[0] == "request" and it[2] is not None)

    def _log_batch(self, items: list[tuple]) -> None:
        import numpy as np

        s, rr = self._stream, self._stream.rr
        cols: dict[str, list[tuple[int, int | None, Any]]] = {}  # entity -> [(t, seq, value)]
        texts: list[tuple[int, int | None, str, str]] = []
        images: list[tuple[int, int | None, tuple]] = []
        for kind, a, b in items:
            if kind == "request":
                f, t, seq = a, int(a["t"]), a.get("seq")
                ok = bool(f.get("ok"))
                tier = f.get("tier") if ok else None
                self._ok += ok
                self._logged += 1
                if ok and f.get("tor_ms") is not None:
                    cols.setdefault(f"{self.results}/tor_ms", []).append((t, seq, float(f["tor_ms"])))
                cols.setdefault(f"{self.results}/tier", []).append((t, seq, float(TIER_LEVEL.get(tier, -1))))
                cols.setdefault(f"{self.results}/ror", []).append((t, seq, self._ok / self._logged))
                line = (f"#{seq} {tier} by {f.get('served_by')} in {float(f.get('tor_ms') or 0):.1f} ms" if ok
                        else f"#{seq} failed: {f.get('error')}")
                texts.append((t, seq, line, "INFO" if ok else "WARN"))
                if f.get("energy_j") is not None:
                    cols.setdefault(f"{self.telemetry}/energy_j", []).append((t, seq, float(f["energy_j"])))
                if f.get("battery") is not None:
                    cols.setdefault(f"{self.telemetry}/battery", []).append((t, seq, float(f["battery"])))
                if b is not None:
                    images.append((t, seq, b))
            elif kind == "alive":
                role, node, up = a
                entity = f"{keys.alive(role, entity_name(node))}/{self.robot}"
                with s._lock:
                    self._step_series(entity, f"{node} seen by {self.robot}")
                cols.setdefault(entity, []).append((b, None, 1.0 if up else 0.0))
            elif kind == "telemetry":
                battery, energy = a
                if battery is not None:
                    cols.setdefault(f"{self.telemetry}/battery", []).append((b, None, float(battery)))
                if energy is not None:
                    cols.setdefault(f"{self.telemetry}/energy_j", []).append((b, None, float(energy)))
        with s._lock:
            for entity, rows in cols.items():
                self._send(entity, rows, rr.Scalars.columns(scalars=[v for _, _, v in rows]), np)
            if texts:
                self._send(f"{self.results}/log", texts,
                           rr.TextLog.columns(text=[x[2] for x in texts], level=[x[3] for x in texts]), np)
        for t, seq, (rgb, mask, srm) in images:  # encoded outside the stream lock
            self._log_images(t, seq, rgb, mask, srm)

    def _send(self, entity: str, rows: list, columns, np) -> None:
        """One column chunk: ``rows`` are ``(t_ns, seq or None, ...)``; ``request`` only when all have one."""
        rr, rec = self._stream.rr, self._stream.rec
        indexes = [rr.TimeColumn("wall_time", timestamp=np.array([r[0] for r in rows], dtype="datetime64[ns]"))]
        if all(r[1] is not None for r in rows):
            indexes.append(rr.TimeColumn("request", sequence=[int(r[1]) for r in rows]))
        rr.send_columns(entity, indexes=indexes, columns=columns, recording=rec)

    def _log_images(self, t: int, seq, rgb, mask, srm) -> None:
        import cv2

        s, rr = self._stream, self._stream.rr
        shape = None
        classes = None
        if mask is not None:
            classes = _mask_to_classes(mask)
            shape = classes.shape
        jpg = srm_jpg = None
        if rgb is not None:
            frame = _rgb(rgb, shape)
            ok, buf = cv2.imencode(".jpg", frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            jpg = buf.tobytes() if ok else None
        if srm is not None:
            ok, buf = cv2.imencode(".jpg", _rgb(srm, None)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
            srm_jpg = buf.tobytes() if ok else None
        with s._lock:
            s.at(t, seq)
            if jpg is not None:
                s.rec.log(self.camera, rr.EncodedImage(contents=jpg, media_type="image/jpeg"))
            if classes is not None:
                s.rec.log(f"{self.camera}/drivable", rr.SegmentationImage(classes, opacity=0.5))
            if srm_jpg is not None:
                s.rec.log(f"{ROBOT_ROOT}/{self.robot}/srm", rr.EncodedImage(contents=srm_jpg, media_type="image/jpeg"))

    def close(self) -> None:
        """Log what is still queued, stop the logger thread, close the stream."""
        self._closed = True
        self._wake.set()
        self._thread.join(timeout=10.0)
        self.flush()
        if self.dropped_images:
            log.warning("rerun: %d frames' images were not logged (the logger fell behind; scalars are complete)",
                        self.dropped_images)
        super().close()


def robot_viz(options: RerunOptions | None, robot: str, **kw: Any) -> RobotViz | None:
    """A :class:`RobotViz` for ``robot``, or ``None`` when ``options`` is ``None``."""
    return None if options is None else RobotViz(options, robot, **kw)


