"""The run plots (OpenCV): ToR per request over time, serving tier per robot over time.

:func:`plot_tor` is the one ToR plot: ``scmr scenario run``'s ``tor.png`` and
``scmr demo``'s ``pictures/timeline.png``; :func:`plot_tiers` is
``tiers.png``.  Both read a report (:mod:`scmr_mesh.scenario.report`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

__all__ = ["TIER_COLOURS", "plot_tiers", "plot_tor", "request_rows"]

#: BGR colours of the tiers in the plots.
TIER_COLOURS = {"cloud": (200, 120, 30), "leader": (30, 140, 240), "peer": (200, 60, 200), "local": (60, 170, 60),
                "failed": (40, 40, 220), "unknown": (128, 128, 128)}


def request_rows(report: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """One row per request: ``request_log`` of a run report (whose ``requests`` is the count), or
    ``requests`` of :func:`~scmr_mesh.scenario.report.build_report`'s view."""
    rows = report.get("request_log")
    if rows is None:
        rows = report.get("requests")
    return list(rows) if isinstance(rows, list) else []


_W, _H, _ML, _MR, _MT, _MB = 1000, 420, 70, 20, 40, 50


def _canvas(title: str):
    import cv2
    import numpy as np

    img = np.full((_H, _W, 3), 255, np.uint8)
    cv2.putText(img, title, (_ML, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return img


_T_MIN = [0.0]  # left edge of the time axis (requests sent before the robots were all ready are < 0)


def _x(t: float, t_max: float) -> int:
    t0 = _T_MIN[0]
    return int(_ML + (_W - _ML - _MR) * ((t - t0) / (t_max - t0) if t_max > t0 else 0))


def _axes(img, t_max: float, faults: Sequence[Mapping[str, Any]]) -> None:
    import cv2

    for f in faults:  # shade fault intervals
        a = f.get("started_at_s")
        b = f.get("ended_at_s")
        if a is None:
            continue
        b = t_max if b is None else b
        x0, x1 = _x(max(_T_MIN[0], a), t_max), _x(min(t_max, b), t_max)
        sub = img[_MT:_H - _MB, x0:max(x0 + 1, x1)]
        sub[:] = (sub * 0.85).astype(sub.dtype)
    cv2.rectangle(img, (_ML, _MT), (_W - _MR, _H - _MB), (0, 0, 0), 1)
    step = max(1, int(math.ceil((t_max - _T_MIN[0]) / 10)))
    for s in range(int(math.ceil(_T_MIN[0])), int(t_max) + 1, step):
        x = _x(s, t_max)
        cv2.line(img, (x, _H - _MB), (x, _H - _MB + 5), (0, 0, 0), 1)
        cv2.putText(img, f"{s}", (x - 5, _H - _MB + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "time since robots started (s); shaded = fault active", (_ML, _H - 8),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)


def _legend(img) -> None:
    import cv2

    x = _W - _MR - 410
    for name, col in TIER_COLOURS.items():
        if name == "unknown":
            continue
        cv2.circle(img, (x, 20), 5, col, -1)
        cv2.putText(img, name, (x + 8, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        x += 80


def _t_max(report: Mapping[str, Any]) -> float:
    ts = [r.get("sent_s") or 0.0 for r in request_rows(report)]
    _T_MIN[0] = math.floor(min([0.0] + ts))
    return max([float(report["duration_s"])] + ts) * 1.02 + 0.1


def plot_tor(report: Mapping[str, Any], path: Path, records: Sequence[Mapping[str, Any]] | None = None) -> Path:
    """Every request's ToR against its sending time, coloured by serving tier (the one ToR plot).

    ``scmr scenario run``'s ``tor.png`` and ``scmr demo``'s ``pictures/timeline.png``.
    Faults that take a tier away are shaded and named; a crash of the leader is a
    marker naming who took the lead; failed requests are crosses on the top edge.

    Parameters
    ----------
    report : report dict (``t0_unix_ns``/``started_unix_ns``, ``duration_s``, ``faults``,
        ``leadership``, and ``requests`` unless ``records`` are given)
    path : Path
        PNG written here, ``(420, 1000, 3) uint8``.
    records : sequence of record dicts, optional
        The robots' records (default: the report's ``requests``).
    """
    import cv2
    import numpy as np

    from scmr_mesh.qos import metrics

    records = request_rows(report) if records is None else list(records)
    img = np.full((_H, _W, 3), 255, np.uint8)
    left, right, top, bottom = 60, 20, 40, 50
    sent = [int(r["sent_unix_ns"]) for r in records if r.get("sent_unix_ns") is not None]
    t_ref = report.get("t0_unix_ns") or report.get("started_unix_ns") or (min(sent) if sent else 0)
    pts = [(r, float(r["sent_s"]) if r.get("sent_s") is not None else (int(r["sent_unix_ns"]) - t_ref) / 1e9)
           for r in records if r.get("sent_s") is not None or r.get("sent_unix_ns") is not None]
    xs = [x for _, x in pts]
    t_min = min([0.0, *xs])
    t_max = max([float(report.get("duration_s", 1.0)), *xs]) or 1.0
    tors = metrics.tor_values_ms(records)
    y_max = max(20.0, metrics.percentile(tors, 99) * 1.3) if tors else 100.0

    def X(t: float) -> int:
        return int(left + (t - t_min) / (t_max - t_min) * (_W - left - right))

    def Y(ms: float) -> int:
        return int(_H - bottom - min(ms, y_max) / y_max * (_H - top - bottom))

    def at(f: Mapping[str, Any], rel: str, ns: str) -> float | None:
        if f.get(ns) is not None:
            return (int(f[ns]) - t_ref) / 1e9
        return f.get(rel)

    moves = {c["from"]: c["to"] for c in (report.get("leadership") or {}).get("changes", []) if c.get("from")}
    for f in report.get("faults", []):
        a = at(f, "started_at_s", "start_unix_ns")
        if a is None:
            continue
        target = f.get("target") or f.get("label") or f.get("kind")
        if f.get("tier") == "leader":  # the lead passes on: a marker, not a lost tier
            cv2.line(img, (X(a), top), (X(a), _H - bottom), TIER_COLOURS["leader"], 1)
            label = f"leader {target} killed" + (f" -> {moves[target]} leads" if target in moves else "")
            cv2.putText(img, label, (X(a) + 4, top + 30), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 90, 160), 1,
                        cv2.LINE_AA)
            continue
        b = at(f, "ended_at_s", "end_unix_ns")
        b = t_max if b is None else b
        cv2.rectangle(img, (X(a), top), (X(b), _H - bottom), (225, 225, 225), -1)
        what = "down" if f.get("kind") == "crash" else str(f.get("kind"))
        cv2.putText(img, f"{target} {what}", (X(a) + 4, top + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (90, 90, 90), 1, cv2.LINE_AA)
    cv2.line(img, (left, _H - bottom), (_W - right, _H - bottom), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, _H - bottom), (0, 0, 0), 1)
    for i in range(5):
        ms = y_max * i / 4
        cv2.putText(img, f"{ms:.0f}", (5, Y(ms) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    step = max(1, int(round((t_max - t_min) / 10)))
    for t in range(int(np.ceil(t_min)), int(t_max) + 1, step):
        cv2.putText(img, f"{t}", (X(t) - 5, _H - bottom + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0),
                    1, cv2.LINE_AA)
    cv2.putText(img, "time since the robots started (s)", (_W // 2 - 120, _H - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "ToR (ms)", (5, top - 22), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for r, x in pts:
        tier = r.get("tier") if r.get("ok") else None
        if tier is None:
            cv2.drawMarker(img, (X(x), top + 4), TIER_COLOURS["failed"], cv2.MARKER_TILTED_CROSS, 8, 2)
            continue
        cv2.circle(img, (X(x), Y(r.get("tor_ms") or 0.0)), 3, TIER_COLOURS.get(tier, TIER_COLOURS["unknown"]),
                   -1, cv2.LINE_AA)
    lx = left + 10
    for name in ("cloud", "leader", "peer", "local", "failed"):
        cv2.circle(img, (lx, top - 8), 5, TIER_COLOURS[name], -1)
        cv2.putText(img, name, (lx + 10, top - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        lx += 90
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)
    return path


def plot_tiers(report: Mapping[str, Any], path: Path) -> Path:
    """Serving tier over time: one row per robot, one tick per request coloured by tier."""
    import cv2

    img = _canvas(f"{report['scenario']}: serving tier per request ({report['backend']})")
    t_max = _t_max(report)
    _axes(img, t_max, report["faults"])
    _legend(img)
    robots = sorted({str(r.get("robot")) for r in request_rows(report)}) or ["-"]
    band = (_H - _MB - _MT) / len(robots)
    for i, rid in enumerate(robots):
        yc = int(_MT + band * (i + 0.5))
        cv2.putText(img, rid, (4, yc + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for r in request_rows(report):
            if str(r.get("robot")) != rid or r.get("sent_s") is None:
                continue
            tier = (r.get("tier") or "unknown") if r.get("ok") else "failed"
            x = _x(float(r["sent_s"]), t_max)
            h = int(band * 0.35)
            cv2.line(img, (x, yc - h), (x, yc + h), TIER_COLOURS.get(tier, TIER_COLOURS["unknown"]), 2)
    path = Path(path)
    cv2.imwrite(str(path), img)
    return path
