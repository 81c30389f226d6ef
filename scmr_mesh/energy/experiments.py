"""The thesis's energy experiments: the Eq 4.9 table and experiment 7's sweep.

Units follow the thesis where it fixes them: "1 MB" = 1048576 bytes and
"1 Mb/s" = 131072 bytes/s (Eq 4.9: 23 Mb/s = 3014656 B/s).  All results are
also given in SI bytes and bytes/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from scmr_mesh.energy.model import (
    MIB,
    PROFILES,
    THESIS_CYCLES,
    THESIS_F,
    THESIS_MBPS,
    Profile,
    break_even_up_Bps,
)
from scmr_mesh.energy.placement import LinkEstimate, Task, energy_terms

__all__ = [
    "EQ49",
    "eq49_table",
    "thesis_literal_eq49",
    "e_saved",
    "numeric_break_even_up_Bps",
    "sweep",
    "plot_sweep",
    "measured_inputs_report",
]

#: The Eq 4.9 worked example: C, D (up and down), B_u, B_d, F.
EQ49 = {"cycles": THESIS_CYCLES, "bytes": MIB, "up_Bps": 3014656.0, "down_Bps": 3670016.0, "cloud_factor": THESIS_F}


def eq49_table(profiles: Sequence[Profile] | None = None) -> dict[str, Any]:
    """Eq 4.2-4.9 for the worked example, one row per profile.

    Returns
    -------
    dict
        ``{"inputs": {...}, "rows": [{"profile", "e_proc_j", "e_idle_j",
        "e_trans_j", "e_cloud_j", "e_saved_j", "decision"}]}``; decision is
        ``"offload"`` when ``e_saved_j > 0`` else ``"local"``.
    """
    profs = list(PROFILES.values()) if profiles is None else list(profiles)
    task = Task(EQ49["cycles"], EQ49["bytes"], EQ49["bytes"])
    link = LinkEstimate(EQ49["up_Bps"], EQ49["down_Bps"])
    rows = []
    for p in profs:
        t = energy_terms(task, p, link, tier="cloud", cloud_factor=EQ49["cloud_factor"])
        rows.append(
            {
                "profile": p.name,
                "e_proc_j": t["e_proc_j"],
                "e_idle_j": t["e_idle_j"],
                "e_trans_j": t["e_trans_j"],
                "e_cloud_j": t["e_cloud_j"],
                "e_saved_j": t["e_saved_j"],
                "decision": "offload" if t["e_saved_j"] > 0 else "local",
            }
        )
    inputs = {
        "cycles": EQ49["cycles"],
        "bytes_up": EQ49["bytes"],
        "bytes_down": EQ49["bytes"],
        "up_Bps": EQ49["up_Bps"],
        "down_Bps": EQ49["down_Bps"],
        "cloud_factor": EQ49["cloud_factor"],
        "source": "assumed: thesis Eq 4.9 and Table 4.3 (C = 5 read as 5e9 cycles)",
    }
    return {"inputs": inputs, "rows": rows}


def thesis_literal_eq49(profile: Profile) -> float:
    """Eq 4.9 exactly as printed: ``P_i * 5 / (P_c * 300) + P_u * D / B_u + P_d * D / B_d``.

    The printed equation divides by ``P_c`` where Eq 4.3/4.8 have ``S_r`` (a
    typo); this reproduces it so docs can show the difference.
    """
    return (
        profile.p_idle_w * 5 / (profile.p_compute_w * 300)
        + profile.p_up_w * MIB / EQ49["up_Bps"]
        + profile.p_down_w * MIB / EQ49["down_Bps"]
    )


def e_saved(
    profile: Profile,
    *,
    cycles: float,
    bytes_up: float,
    bytes_down: float,
    up_Bps: float,
    down_up_ratio: float = 1.0,
    cloud_factor: float = THESIS_F,
) -> float:
    """``E_saved`` (Eq 4.5) for offloading to the cloud at upload rate ``up_Bps``, J."""
    task = Task(cycles, int(bytes_up), int(bytes_down))
    link = LinkEstimate(up_Bps, up_Bps * down_up_ratio)
    return energy_terms(task, profile, link, tier="cloud", cloud_factor=cloud_factor)["e_saved_j"]


def numeric_break_even_up_Bps(
    profile: Profile,
    *,
    cycles: float,
    bytes_up: float,
    bytes_down: float,
    down_up_ratio: float = 1.0,
    cloud_factor: float = THESIS_F,
    lo: float = 1.0,
    hi: float = 1e15,
    rel_tol: float = 1e-9,
) -> float:
    """Break-even upload rate found by bisection on ``E_saved(B) = 0``, B/s.

    A numerical cross-check of :func:`~scmr_mesh.energy.model.break_even_up_Bps`
    (``E_saved`` increases with ``B``).  Returns ``inf`` when ``E_saved < 0``
    even at ``hi`` and ``lo`` when it is already >= 0 at ``lo``.
    """
    def f(b: float) -> float:
        return e_saved(
            profile,
            cycles=cycles,
            bytes_up=bytes_up,
            bytes_down=bytes_down,
            up_Bps=b,
            down_up_ratio=down_up_ratio,
            cloud_factor=cloud_factor,
        )

    if f(hi) < 0:
        return math.inf
    if f(lo) >= 0:
        return lo
    a, b = lo, hi
    while b / a - 1 > rel_tol:
        m = math.sqrt(a * b)
        if f(m) < 0:
            a = m
        else:
            b = m
    return math.sqrt(a * b)


def sweep(
    profiles: Sequence[Profile],
    *,
    sizes_bytes: Sequence[int],
    bandwidths_Bps: Sequence[float],
    cycles: float = THESIS_CYCLES,
    reply_bytes: int | None = None,
    down_up_ratio: float = 1.0,
    cloud_factor: float = THESIS_F,
) -> dict[str, Any]:
    """Experiment 7: ``E_saved`` over image size x bandwidth, per profile.

    Parameters
    ----------
    profiles : sequence of Profile
    sizes_bytes : sequence of int
        Upload sizes ``D_up``, bytes.
    bandwidths_Bps : sequence of float
        Upload rates ``B_u``, bytes/s; ``B_d = down_up_ratio * B_u``.
    cycles : float
        ``C``, cycles per task (thesis: 5e9).
    reply_bytes : int, optional
        ``D_down``; default equal to the upload size, as in the thesis.
    down_up_ratio : float
    cloud_factor : float

    Returns
    -------
    dict
        ``{"params", "profiles": [{"profile", "grid": [{"size_bytes",
        "bandwidth_Bps", "bandwidth_mbps", "e_saved_j"}], "break_even":
        [{"size_bytes", "closed_form_Bps", "numeric_Bps", "closed_form_mbps",
        "rel_diff"}]}]}``.
    """
    out_profiles = []
    for p in profiles:
        grid = []
        breaks = []
        for d in sizes_bytes:
            down = d if reply_bytes is None else reply_bytes
            for b in bandwidths_Bps:
                grid.append(
                    {
                        "size_bytes": int(d),
                        "bandwidth_Bps": float(b),
                        "bandwidth_mbps": float(b) / THESIS_MBPS,
                        "e_saved_j": e_saved(
                            p,
                            cycles=cycles,
                            bytes_up=d,
                            bytes_down=down,
                            up_Bps=b,
                            down_up_ratio=down_up_ratio,
                            cloud_factor=cloud_factor,
                        ),
                    }
                )
            kw = dict(cycles=cycles, bytes_up=d, bytes_down=down, down_up_ratio=down_up_ratio, cloud_factor=cloud_factor)
            closed = break_even_up_Bps(p, **kw)
            numeric = numeric_break_even_up_Bps(p, **kw)
            rel = abs(closed - numeric) / closed if math.isfinite(closed) and closed > 0 else 0.0
            breaks.append(
                {
                    "size_bytes": int(d),
                    "closed_form_Bps": closed,
                    "numeric_Bps": numeric,
                    "closed_form_mbps": closed / THESIS_MBPS,
                    "rel_diff": rel,
                }
            )
        out_profiles.append({"profile": p.name, "grid": grid, "break_even": breaks})
    return {
        "params": {
            "cycles": cycles,
            "sizes_bytes": [int(d) for d in sizes_bytes],
            "bandwidths_Bps": [float(b) for b in bandwidths_Bps],
            "reply_bytes": reply_bytes,
            "down_up_ratio": down_up_ratio,
            "cloud_factor": cloud_factor,
            "mbps_unit_Bps": THESIS_MBPS,
            "mb_unit_bytes": MIB,
            "source": "assumed: thesis Table 4.3 profiles and C = 5e9 cycles unless overridden",
        },
        "profiles": out_profiles,
    }


_COLOURS = [(200, 80, 0), (0, 140, 0), (0, 0, 220), (160, 0, 160), (0, 150, 200), (90, 90, 90), (0, 80, 160)]


def plot_sweep(result: dict[str, Any], path: str | Path, *, panel_w: int = 520, panel_h: int = 360) -> Path:
    """Draw the sweep as one panel per profile (``E_saved`` vs bandwidth, a
    line per size, break-even marks) with OpenCV and write a PNG.

    Returns
    -------
    Path
        The written file.
    """
    import cv2
    import numpy as np

    from scmr_mesh.errors import InputError

    profs = result["profiles"]
    n = len(profs)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    img = np.full((rows * panel_h, cols * panel_w, 3), 255, np.uint8)
    sizes = result["params"]["sizes_bytes"]
    bws = result["params"]["bandwidths_Bps"]
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i, pr in enumerate(profs):
        ox, oy = (i % cols) * panel_w, (i // cols) * panel_h
        left, right, top, bottom = ox + 60, ox + panel_w - 15, oy + 30, oy + panel_h - 45
        vals = [g["e_saved_j"] for g in pr["grid"]]
        vmin, vmax = min(min(vals), 0.0), max(max(vals), 0.0)
        if vmax > 0:  # keep the zero crossing readable: clip deep losses at -2x the best saving
            vmin = max(vmin, -2.0 * vmax)
        if vmax == vmin:
            vmax = vmin + 1.0
        bmin, bmax = min(bws), max(bws)
        span_b = (bmax - bmin) or 1.0

        def px(b: float, v: float) -> tuple[int, int]:
            x = left + (b - bmin) / span_b * (right - left)
            y = bottom - (min(max(v, vmin), vmax) - vmin) / (vmax - vmin) * (bottom - top)
            return int(round(x)), int(round(y))

        cv2.rectangle(img, (left, top), (right, bottom), (0, 0, 0), 1)
        if vmin > min(vals):
            cv2.putText(img, "(losses clipped)", (left + 5, bottom - 6), font, 0.38, (90, 90, 90), 1)
        y0 = px(bmin, 0.0)[1]
        cv2.line(img, (left, y0), (right, y0), (120, 120, 120), 1)
        cv2.putText(img, f"{pr['profile']}: E_saved (J) vs bandwidth (Mb/s)", (ox + 10, oy + 18), font, 0.5, (0, 0, 0), 1)
        for v in (vmin, 0.0, vmax):
            cv2.putText(img, f"{v:.0f}", (ox + 5, px(bmin, v)[1] + 4), font, 0.38, (0, 0, 0), 1)
        for b in (bmin, (bmin + bmax) / 2, bmax):
            x = px(b, 0.0)[0]
            cv2.putText(img, f"{b / THESIS_MBPS:.0f}", (x - 10, bottom + 16), font, 0.38, (0, 0, 0), 1)
        for j, d in enumerate(sizes):
            colour = _COLOURS[j % len(_COLOURS)]
            pts = [px(g["bandwidth_Bps"], g["e_saved_j"]) for g in pr["grid"] if g["size_bytes"] == d]
            if len(pts) > 1:
                cv2.polylines(img, [np.array(pts, np.int32)], False, colour, 2, cv2.LINE_AA)
            be = pr["break_even"][j]["closed_form_Bps"]
            if math.isfinite(be) and bmin <= be <= bmax:
                cv2.circle(img, px(be, 0.0), 5, colour, 2, cv2.LINE_AA)
            label = f"{d / MIB:g} MB"
            cv2.putText(img, label, (left + 8 + 70 * j, bottom + 34), font, 0.42, colour, 1, cv2.LINE_AA)
    out = Path(path)
    ok = False
    try:
        ok = cv2.imwrite(str(out), img)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(f"could not write the plot to {out}; give a writable path ending in .png")
    return out


def _pct(values: Sequence[float], q: float) -> float:
    xs = sorted(values)
    if not xs:
        return math.nan
    k = (len(xs) - 1) * q / 100.0
    lo, hi = math.floor(k), math.ceil(k)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def measured_inputs_report(
    samples: Sequence[dict[str, float]],
    profiles: Sequence[Profile],
    *,
    host_hz: float,
    host_hz_source: str,
    up_Bps: float = EQ49["up_Bps"],
    down_Bps: float = EQ49["down_Bps"],
    cloud_factor: float = THESIS_F,
) -> dict[str, Any]:
    """Eq 4.2-4.6 per profile with ``C``, ``D_up``, ``D_down`` measured on real frames.

    Parameters
    ----------
    samples : sequence of dict
        Per frame: ``cpu_s`` (pipeline thread CPU time here), ``bytes_up``
        (encoded frame), ``bytes_down`` (mask PNG).
    profiles : sequence of Profile
    host_hz, host_hz_source : float, str
        This host's clock and where it came from.
    up_Bps, down_Bps : float
        Link rates (assumed: Eq 4.9's 23 / 28 Mb/s unless given).

    Returns
    -------
    dict
        ``{"frames", "cpu_s", "cycles", "bytes_up", "bytes_down"`` (each with
        median / p99), ``"inputs"`` (each marked measured/assumed), ``"rows"``
        per profile at the median frame: e_proc_j, e_cloud_j, e_saved_j,
        decision, local_s, remote_s, break_even_mbps``}``.
    """
    cpu = [s["cpu_s"] for s in samples]
    up = [s["bytes_up"] for s in samples]
    down = [s["bytes_down"] for s in samples]
    stats = {
        name: {"median": _pct(vals, 50), "p99": _pct(vals, 99), "min": min(vals), "max": max(vals)}
        for name, vals in (("cpu_s", cpu), ("bytes_up", up), ("bytes_down", down))
    }
    cycles_med = stats["cpu_s"]["median"] * host_hz
    stats["cycles"] = {k: v * host_hz for k, v in stats["cpu_s"].items()}
    task = Task(cycles_med, int(round(stats["bytes_up"]["median"])), int(round(stats["bytes_down"]["median"])))
    link = LinkEstimate(up_Bps, down_Bps)
    rows = []
    for p in profiles:
        t = energy_terms(task, p, link, cloud_factor=cloud_factor)
        be = break_even_up_Bps(
            p, cycles=task.cycles, bytes_up=task.bytes_up, bytes_down=task.bytes_down,
            down_up_ratio=down_Bps / up_Bps, cloud_factor=cloud_factor,
        )
        rows.append(
            {
                "profile": p.name,
                "e_proc_j": t["e_proc_j"],
                "e_cloud_j": t["e_cloud_j"],
                "e_saved_j": t["e_saved_j"],
                "decision": "offload" if t["e_saved_j"] > 0 else "local",
                "local_s": t["local_s"],
                "remote_s": t["remote_s"],
                "break_even_mbps": be / THESIS_MBPS if math.isfinite(be) else None,
            }
        )
    return {
        "frames": len(samples),
        **stats,
        "inputs": {
            "cycles": {"value": cycles_med, "source": f"measured: median pipeline CPU time x host clock ({host_hz_source})"},
            "bytes_up": {"value": task.bytes_up, "source": "measured: median encoded frame size"},
            "bytes_down": {"value": task.bytes_down, "source": "measured: median mask PNG size"},
            "up_Bps": {"value": up_Bps, "source": "assumed"},
            "down_Bps": {"value": down_Bps, "source": "assumed"},
            "powers_and_clocks": {"value": "profiles", "source": "assumed (thesis Table 4.3 or user file)"},
            "cloud_factor": {"value": cloud_factor, "source": "assumed"},
        },
        "rows": rows,
    }
