"""Reports from hand-made records: gaps, expectations, energy, thesis table, Markdown and PNG plots."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from scmr_mesh.scenario.report import (
    build_report,
    energy_per_robot,
    thesis_table,
    write_report,
)
from scmr_mesh.scenario.spec import parse_scenario

S = 1_000_000_000
T0 = 1_700_000_000 * S

SC = parse_scenario({
    "name": "r", "seed": 42, "duration_s": 4,
    "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "profile": "robot1"}]},
    "faults": [{"kind": "link_down", "at_s": 1.0, "for_s": 1.0, "link": ["robot1", "cloud"]}],
    "expectations": [{"metric": "ror", "op": ">=", "value": 1.0},
                     {"metric": "max_failover_gap_ms", "op": "<=", "value": 300},
                     {"metric": "max_failback_gap_ms", "op": "<=", "value": 100}],
})


def rec(seq, sent_s, tor_ms, tier, ok=True):
    sent = T0 + int(sent_s * S)
    return {"robot": "robot1", "seq": seq, "image": f"f{seq}", "bytes_up": 1000, "bytes_down": 500,
            "sent_unix_ns": sent, "received_unix_ns": sent + int(tor_ms * 1e6), "tor_ms": tor_ms, "ok": ok,
            "tier": tier if ok else None, "served_by": tier, "attempts": [], "error": None if ok else "x"}


RECORDS = [rec(0, 0.5, 10, "cloud"), rec(1, 0.95, 250, "leader"),  # in flight at the cut, then leader
           rec(2, 1.5, 20, "leader"), rec(3, 2.1, 30, "leader"), rec(4, 2.3, 10, "cloud")]
FAULTS = [{"kind": "link_down", "label": "link_down robot1-cloud", "at_s": 1.0, "for_s": 1.0, "tier": "cloud",
           "robots": ["robot1"], "start_unix_ns": T0 + 1 * S, "end_unix_ns": T0 + 2 * S}]


@pytest.fixture(scope="module")
def report():
    return build_report(SC, RECORDS, FAULTS, t0_unix_ns=T0, backend="test")


def test_gaps_follow_the_shared_definitions(report):
    f = report["faults"][0]
    # first failed-by-cloud request was sent at 0.95 s (before the cut): t0 = the cut at 1.0 s;
    # first leader answer received at 0.95 + 0.25 = 1.2 s -> 200 ms
    assert f["failover_gap_ms"] == pytest.approx(200.0)
    # the link returned at 2.0 s; first cloud answer at 2.3 + 0.01 s -> 310 ms
    assert f["failback_gap_ms"] == pytest.approx(310.0)
    assert f["started_at_s"] == 1.0 and f["ended_at_s"] == 2.0


def test_expectations_and_summary(report):
    held = {e["name"]: e["held"] for e in report["expectations"]}
    # the default telemetry expectation fails when telemetry was not counted (no block given)
    assert held == {"ror >= 1": True, "max_failover_gap_ms <= 300": True, "max_failback_gap_ms <= 100": False,
                    "telemetry_lost <= 0": False}
    assert report["passed"] is False
    s = report["summary"]
    assert (s["requests"], s["succeeded"], s["ror"]) == (5, 5, 1.0)
    assert s["by_tier"]["leader"] == 3 and s["by_tier"]["cloud"] == 2
    assert report["seed"] == 42 and len(report["requests"]) == 5


def test_every_scenario_expects_no_telemetry_lost_unless_it_says_otherwise():
    """Issue #12, item 3: a default expectation of zero telemetry lost."""
    import dataclasses

    from scmr_mesh.scenario.spec import Expectation

    ok = {"sent": 10, "stored": 10, "duplicates": 0, "lost": 0, "per_robot": {}}
    lost = {"sent": 10, "stored": 7, "duplicates": 0, "lost": 3, "per_robot": {}}
    sc = dataclasses.replace(SC, expectations=(Expectation("ror", ">=", 1.0),))

    def tel_exp(rep):
        return next(e for e in rep["expectations"] if e["metric"] == "telemetry_lost")

    rep = build_report(sc, RECORDS, FAULTS, t0_unix_ns=T0, backend="test", telemetry=ok)
    assert tel_exp(rep) == {"name": "telemetry_lost <= 0", "metric": "telemetry_lost", "observed": 0, "held": True}
    assert rep["passed"] is True
    rep = build_report(sc, RECORDS, FAULTS, t0_unix_ns=T0, backend="test", telemetry=lost)
    assert tel_exp(rep)["observed"] == 3 and rep["passed"] is False
    loose = dataclasses.replace(sc, expectations=(Expectation("telemetry_lost", "<=", 5.0),))
    rep = build_report(loose, RECORDS, FAULTS, t0_unix_ns=T0, backend="test", telemetry=lost)
    assert [e["name"] for e in rep["expectations"]] == ["telemetry_lost <= 5"] and rep["passed"] is True


def test_failed_requests_lower_ror_and_unmeasured_gaps_fail():
    recs = [rec(0, 0.5, 10, "cloud"), rec(1, 1.2, 0, None, ok=False)]
    rep = build_report(SC, recs, FAULTS, t0_unix_ns=T0, backend="test")
    assert rep["summary"]["ror"] == 0.5
    by = {e["metric"]: e for e in rep["expectations"]}
    assert by["max_failover_gap_ms"]["observed"] is None and not by["max_failover_gap_ms"]["held"]


def test_energy_per_robot_follows_the_model():
    from scmr_mesh.energy import get_profile

    p = get_profile("robot1")
    e = energy_per_robot(SC, [rec(0, 0.0, 1000, "cloud")])["robot1"]
    want = p.p_idle_w * 1.0 + p.p_up_w * 1000 / (23 * 131072) + p.p_down_w * 500 / (28 * 131072)
    assert e["total_j"] == pytest.approx(want) and e["source"] == "model"
    led = energy_per_robot(SC, [dict(rec(0, 0.0, 1000, "cloud"), energy_j=3.5)])["robot1"]
    assert led["total_j"] == 3.5 and led["source"] == "robot ledger"


def test_thesis_table_matches_the_csv(roads_dir):
    path = roads_dir.parent / "thesis_table_4_2.csv"
    t = thesis_table(path)
    rows = [r for r in csv.DictReader(path.open()) if r["robot"] == "Robot 4"]
    tors = sorted(float(r["download_end_ms"]) - float(r["upload_start_ms"]) for r in rows)
    assert t["robot4"]["images"] == len(rows) == 5
    assert t["robot4"]["cloud_tor_p50_ms"] == tors[2]
    assert thesis_table(Path("/nonexistent.csv")) is None


def test_write_report_markdown_and_plots(report, tmp_path):
    paths = write_report(report, tmp_path)
    md = paths["md"].read_text()
    for heading in ("## Expectations", "## Summary", "### Per robot", "## Faults", "## Energy per robot",
                    "## Requests", "![tor](tor.png)"):
        assert heading in md
    assert "FAILED" in md and "| link_down robot1-cloud |" in md
    for key in ("tor_png", "tiers_png"):
        img = cv2.imread(str(paths[key]))
        assert img is not None and img.shape == (420, 1000, 3)
        # leader dots are drawn in the leader colour (BGR 30,140,240)
        assert np.any(np.all(img == (30, 140, 240), axis=2))


def test_every_serving_tier_has_its_own_colour_in_the_plots():
    """Frames served by a peer robot were drawn grey ('unknown') with no legend entry."""
    from scmr_mesh.qos.metrics import TIERS
    from scmr_mesh.scenario.report import TIER_COLOURS

    colours = [TIER_COLOURS[t] for t in TIERS]
    assert len(set(colours)) == len(TIERS) and TIER_COLOURS["unknown"] not in colours
