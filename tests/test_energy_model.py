"""Energy model (thesis Eq 4.2-4.6, 4.9): hand-computed values, cross-checks, properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.energy import (
    PROFILES,
    LinkEstimate,
    Profile,
    Task,
    break_even_up_Bps,
    energy_terms,
)
from scmr_mesh.energy.experiments import (
    eq49_table,
    numeric_break_even_up_Bps,
    sweep,
    thesis_literal_eq49,
)
from scmr_mesh.energy.model import e_idle, e_proc, e_trans

# Eq 4.9 by hand: D/B_u = 1048576/3014656 = 8/23, D/B_d = 1048576/3670016 = 2/7.
EQ49_TASK = Task(5e9, 1048576, 1048576)
EQ49_LINK = LinkEstimate(3014656, 3670016)


def test_e_proc_by_hand():
    # 47 W * 5e9 cycles / 1e9 Hz = 235 J
    assert e_proc(5e9, p_compute_w=47.0, clock_hz=1e9) == pytest.approx(235.0)
    # 177 W * 5e9 / 3.5e9 = 252.857142... J
    assert e_proc(5e9, p_compute_w=177.0, clock_hz=3.5e9) == pytest.approx(252.857142857)


def test_e_idle_by_hand():
    # 25 W * 5e9 / (300 * 1e9) = 0.416666... J
    assert e_idle(5e9, p_idle_w=25.0, remote_hz=300e9) == pytest.approx(0.4166666667)
    # rtt extension: idle power also over the round trip: 25 W * (1/60 s + 0.1 s) = 2.9166... J
    assert e_idle(5e9, p_idle_w=25.0, remote_hz=300e9, rtt_s=0.1) == pytest.approx(2.9166666667)


def test_e_trans_by_hand():
    # 83.54 * 8/23 + 104.08 * 2/7 = 29.057391 + 29.737143 = 58.794534 J
    got = e_trans(1048576, 1048576, p_up_w=83.54, p_down_w=104.08, up_Bps=3014656, down_Bps=3670016)
    assert got == pytest.approx(58.794534, abs=1e-5)
    assert e_trans(0, 0, p_up_w=1.0, p_down_w=1.0, up_Bps=1.0, down_Bps=1.0) == 0.0


def test_energy_terms_robot1_by_hand():
    t = energy_terms(EQ49_TASK, PROFILES["robot1"], EQ49_LINK)
    assert t["e_proc_j"] == pytest.approx(235.0)
    assert t["e_idle_j"] == pytest.approx(0.4166666667)
    assert t["e_trans_j"] == pytest.approx(58.794534, abs=1e-5)
    assert t["e_cloud_j"] == pytest.approx(59.211201, abs=1e-5)
    assert t["e_saved_j"] == pytest.approx(175.788799, abs=1e-5)
    # predicted times: local 5 s; remote 8/23 + 5e9/3e11 + 2/7 s
    assert t["local_s"] == pytest.approx(5.0)
    assert t["remote_s"] == pytest.approx(8 / 23 + 1 / 60 + 2 / 7)


def test_eq49_table_leader_by_hand_and_decisions():
    rows = {r["profile"]: r for r in eq49_table()["rows"]}
    assert list(rows) == ["leader", "robot1", "robot2", "robot3", "robot4"]
    lead = rows["leader"]
    # 177*5/3.5; 99*5/1050; 314.61*8/23 + 391.98*2/7
    assert lead["e_proc_j"] == pytest.approx(252.857143, abs=1e-5)
    assert lead["e_idle_j"] == pytest.approx(0.471429, abs=1e-5)
    assert lead["e_trans_j"] == pytest.approx(109.429565 + 111.994286, abs=1e-5)
    assert lead["e_saved_j"] == pytest.approx(252.857143 - 0.471429 - 221.423851, abs=1e-5)
    for r in rows.values():
        assert set(r) == {"profile", "e_proc_j", "e_idle_j", "e_trans_j", "e_cloud_j", "e_saved_j", "decision"}
        assert r["decision"] == ("offload" if r["e_saved_j"] > 0 else "local")


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_eq49_rows_match_eq46_form(name):
    """Eq 4.6 rearranges Eq 4.5: E_saved = C/S_r * (P_c - P_i/F) - E_trans."""
    p = PROFILES[name]
    row = next(r for r in eq49_table()["rows"] if r["profile"] == name)
    eq46 = 5e9 / p.clock_hz * (p.p_compute_w - p.p_idle_w / 300) - (
        p.p_up_w * 1048576 / 3014656 + p.p_down_w * 1048576 / 3670016
    )
    assert row["e_saved_j"] == pytest.approx(eq46, rel=1e-12)


def test_thesis_literal_eq49_differs_only_in_idle_term():
    """The printed Eq 4.9 divides by P_c instead of S_r: only E_idle changes."""
    for p in PROFILES.values():
        ours = energy_terms(EQ49_TASK, p, EQ49_LINK)
        literal = thesis_literal_eq49(p)
        assert literal - ours["e_trans_j"] == pytest.approx(p.p_idle_w * 5 / (p.p_compute_w * 300))
        assert literal != pytest.approx(ours["e_cloud_j"], abs=1e-6)


@pytest.mark.parametrize("name", sorted(PROFILES))
@pytest.mark.parametrize("size", [524288, 1048576, 3145728])
@pytest.mark.parametrize("ratio", [1.0, 28 / 23])
def test_break_even_closed_form_matches_bisection(name, size, ratio):
    p = PROFILES[name]
    kw = dict(cycles=5e9, bytes_up=size, bytes_down=size, down_up_ratio=ratio)
    closed = break_even_up_Bps(p, **kw)
    assert numeric_break_even_up_Bps(p, **kw) == pytest.approx(closed, rel=1e-6)
    # and E_saved is ~0 there, negative below, positive above
    link = lambda b: LinkEstimate(b, b * ratio)  # noqa: E731
    task = Task(5e9, size, size)
    assert energy_terms(task, p, link(closed))["e_saved_j"] == pytest.approx(0.0, abs=1e-6)
    assert energy_terms(task, p, link(closed * 0.99))["e_saved_j"] < 0
    assert energy_terms(task, p, link(closed * 1.01))["e_saved_j"] > 0


def test_break_even_never_when_idle_dominates():
    p = Profile("odd", p_compute_w=1.0, p_idle_w=600.0, p_up_w=1.0, p_down_w=1.0, clock_hz=1e9, source="test")
    assert break_even_up_Bps(p, cycles=1e9, bytes_up=10, bytes_down=10) == math.inf
    assert numeric_break_even_up_Bps(p, cycles=1e9, bytes_up=10, bytes_down=10) == math.inf


def test_sweep_grid_and_break_even_linear_in_size():
    res = sweep([PROFILES["leader"]], sizes_bytes=[1048576, 3145728], bandwidths_Bps=[25 * 131072, 70 * 131072])
    pr = res["profiles"][0]
    assert len(pr["grid"]) == 4
    b1, b3 = (b["closed_form_Bps"] for b in pr["break_even"])
    assert b3 == pytest.approx(3 * b1)  # E_trans is linear in D, so is the break-even bandwidth
    assert all(b["rel_diff"] < 1e-6 for b in pr["break_even"])


profiles_st = st.builds(
    Profile,
    name=st.just("h"),
    p_compute_w=st.floats(1, 500),
    p_idle_w=st.floats(0.1, 200),
    p_up_w=st.floats(0.1, 500),
    p_down_w=st.floats(0.1, 500),
    clock_hz=st.floats(1e8, 5e9),
)


@settings(max_examples=150, deadline=None)
@given(
    p=profiles_st,
    cycles=st.floats(1e6, 1e12),
    d=st.integers(0, 10**8),
    b1=st.floats(1e3, 1e10),
    factor=st.floats(1.0, 100.0),
)
def test_more_bandwidth_never_lowers_e_saved(p, cycles, d, b1, factor):
    task = Task(cycles, d, d)
    lo = energy_terms(task, p, LinkEstimate(b1, b1))["e_saved_j"]
    hi = energy_terms(task, p, LinkEstimate(b1 * factor, b1 * factor))["e_saved_j"]
    assert hi >= lo - 1e-9 * abs(lo)


@settings(max_examples=150, deadline=None)
@given(
    p=profiles_st,
    cycles=st.floats(1e6, 1e12),
    d1=st.integers(0, 10**8),
    extra=st.integers(0, 10**8),
    bu=st.floats(1e3, 1e10),
    bd=st.floats(1e3, 1e10),
)
def test_bigger_data_never_raises_e_saved(p, cycles, d1, extra, bu, bd):
    link = LinkEstimate(bu, bd)
    small = energy_terms(Task(cycles, d1, d1), p, link)["e_saved_j"]
    big = energy_terms(Task(cycles, d1 + extra, d1 + extra), p, link)["e_saved_j"]
    assert big <= small + 1e-9 * abs(small)
