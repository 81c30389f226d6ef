"""Placement policy: least robot energy among reachable options meeting the deadline."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.energy import (
    PROFILES,
    LinkEstimate,
    Profile,
    Task,
    choose_placement,
    energy_terms,
)
from scmr_mesh.errors import InputError

EQ49_LINK = LinkEstimate(3014656, 3670016)
TASK = Task(5e9, 1048576, 1048576)


def test_offloads_when_it_saves_energy_and_matches_table():
    p = choose_placement(TASK, PROFILES["robot1"], reachable=["cloud"], links={"cloud": EQ49_LINK})
    assert p.tier == "cloud" and not p.deadline_missed
    assert p.robot_energy_j == pytest.approx(energy_terms(TASK, PROFILES["robot1"], EQ49_LINK)["e_cloud_j"])
    assert "leader not reachable" in p.reason


def test_runs_locally_when_nothing_reachable():
    p = choose_placement(TASK, PROFILES["robot1"], reachable=[], links={"cloud": EQ49_LINK, "leader": EQ49_LINK})
    assert p.tier == "local"
    assert p.robot_energy_j == pytest.approx(235.0)
    assert [o["tier"] for o in p.options] == ["local"]


def test_runs_locally_when_offloading_costs_more():
    slow = LinkEstimate(100_000, 100_000)  # 1 MiB each way at 100 kB/s costs far more than 235 J
    p = choose_placement(TASK, PROFILES["robot1"], reachable=["cloud"], links={"cloud": slow})
    assert p.tier == "local" and not p.deadline_missed


def test_tie_goes_local():
    """Thesis 3.5.4: robotic execution when E_r <= E_c."""
    prof = Profile("t", p_compute_w=10.0, p_idle_w=0.0001, p_up_w=1.0, p_down_w=1.0, clock_hz=1e9, source="t")
    task = Task(1e9, 0, 0)
    # remote: idle only, = P_i * C / remote_hz; choose remote_hz so it equals local 10 J
    link = LinkEstimate(1.0, 1.0, remote_hz=1e9 * 0.0001 / 10.0)
    p = choose_placement(task, prof, reachable=["cloud"], links={"cloud": link})
    assert p.options[1]["robot_energy_j"] == pytest.approx(p.options[0]["robot_energy_j"])
    assert p.tier == "local"


def test_leader_defaults_to_leader_clock_and_cloud_to_f_times_robot():
    p = choose_placement(
        TASK, PROFILES["robot2"], reachable=["cloud", "leader"], links={"cloud": EQ49_LINK, "leader": EQ49_LINK}
    )
    hz = {o["tier"]: o.get("remote_hz") for o in p.options}
    assert hz["cloud"] == pytest.approx(300 * 2.3e9)
    assert hz["leader"] == pytest.approx(3.5e9)
    # same link, slower server: the leader costs more idle energy, so the cloud wins
    assert p.tier == "cloud"


def test_cloud_lost_fails_over_to_leader():
    links = {"cloud": EQ49_LINK, "leader": EQ49_LINK}
    p = choose_placement(TASK, PROFILES["robot1"], reachable=["leader"], links=links)
    assert p.tier == "leader"
    assert "cloud not reachable" in p.reason


def test_deadline_excludes_cheaper_slow_option():
    # Leader: 4x the cloud's bandwidth, so less transfer energy (14.7 + 35.7 idle J < 59.2 J),
    # but its 3.5 GHz clock needs 1.43 s of compute; the cloud answers in 0.65 s.
    links = {"cloud": EQ49_LINK, "leader": LinkEstimate(4 * 3014656, 4 * 3670016)}
    free = choose_placement(TASK, PROFILES["robot1"], reachable=["cloud", "leader"], links=links)
    tight = choose_placement(
        Task(5e9, 1048576, 1048576, deadline_s=1.0), PROFILES["robot1"], reachable=["cloud", "leader"], links=links
    )
    assert free.tier == "leader"  # least energy without a deadline
    assert tight.tier == "cloud" and not tight.deadline_missed
    assert tight.predicted_s <= 1.0


def test_deadline_miss_is_flagged_and_fastest_chosen():
    task = Task(5e9, 1048576, 1048576, deadline_s=0.01)
    p = choose_placement(task, PROFILES["robot1"], reachable=["cloud"], links={"cloud": EQ49_LINK})
    assert p.deadline_missed
    assert p.predicted_s == min(o["predicted_s"] for o in p.options)
    assert "no option meets deadline" in p.reason
    local_only = choose_placement(task, PROFILES["robot1"], reachable=[], links={})
    assert local_only.tier == "local" and local_only.deadline_missed


def test_reachable_tier_without_link_is_left_out():
    p = choose_placement(TASK, PROFILES["robot1"], reachable=["cloud", "leader"], links={"leader": EQ49_LINK})
    assert p.tier == "leader"
    assert "cloud has no link estimate" in p.reason


def test_unknown_tier_name_is_an_input_error():
    with pytest.raises(InputError, match="clouds"):
        choose_placement(TASK, PROFILES["robot1"], reachable=["clouds"], links={})


def test_bad_task_values_are_input_errors():
    with pytest.raises(InputError, match="cycles"):
        Task(0, 1, 1)
    with pytest.raises(InputError, match="deadline"):
        Task(1e9, 1, 1, deadline_s=-1)
    with pytest.raises(InputError, match="up_Bps"):
        LinkEstimate(0, 1)


def test_inputs_are_marked_measured_or_assumed():
    task = Task(1e9, 1000, 100, measured=frozenset({"cycles", "bytes_up", "bytes_down"}))
    links = {"cloud": LinkEstimate(1e6, 1e6, measured=True), "leader": LinkEstimate(1e6, 1e6)}
    p = choose_placement(task, PROFILES["robot3"], reachable=["cloud", "leader"], links=links)
    src = {k: v["source"] for k, v in p.inputs.items()}
    assert src["cycles"] == src["bytes_up"] == src["bytes_down"] == "measured"
    assert src["cloud.up_Bps"] == "measured" and src["leader.up_Bps"] == "assumed"
    assert src["p_compute_w"] == src["clock_hz"] == "assumed"
    assert set(src.values()) <= {"measured", "assumed"}


DVS_PROFILE = Profile(
    "dvs", p_compute_w=40.0, p_idle_w=10.0, p_up_w=50.0, p_down_w=50.0, clock_hz=4e9,
    dvs_levels_hz=(1e9, 2e9, 3e9, 4e9), source="test",
)


@pytest.mark.parametrize(
    "deadline, level",
    [(None, 1e9), (3.0, 1e9), (2.9, 2e9), (1.5, 2e9), (1.49, 3e9), (1.0, 3e9), (0.9, 4e9)],
)
def test_dvs_picks_lowest_sufficient_clock(deadline, level):
    task = Task(3e9, 0, 0, deadline_s=deadline)
    p = choose_placement(task, DVS_PROFILE, reachable=[], links={}, dvs=True)
    local = p.options[0]
    assert local["clock_hz"] == level
    # k = P_c / S_r^3, energy per cycle k f^2; at the nominal clock it equals Eq 4.2
    assert local["robot_energy_j"] == pytest.approx(3e9 * (40.0 / 4e9**3) * level**2)
    assert not p.deadline_missed


def test_dvs_at_nominal_clock_equals_eq42_and_miss_uses_top_clock():
    task = Task(3e9, 0, 0, deadline_s=0.5)  # needs 6 GHz: impossible
    p = choose_placement(task, DVS_PROFILE, reachable=[], links={}, dvs=True)
    assert p.deadline_missed and p.options[0]["clock_hz"] == 4e9
    assert p.robot_energy_j == pytest.approx(40.0 * 3e9 / 4e9)  # Eq 4.2 at S_r


def test_default_dvs_ladder_is_fractions_of_clock():
    assert PROFILES["robot1"].dvs_levels() == pytest.approx((0.4e9, 0.5e9, 0.6e9, 0.7e9, 0.8e9, 0.9e9, 1e9))


links_st = st.builds(
    LinkEstimate,
    up_Bps=st.floats(1e3, 1e9),
    down_Bps=st.floats(1e3, 1e9),
    rtt_s=st.floats(0, 2),
    remote_hz=st.one_of(st.none(), st.floats(1e8, 1e12)),
)


@settings(max_examples=200, deadline=None)
@given(
    name=st.sampled_from(sorted(PROFILES)),
    cycles=st.floats(1e6, 1e11),
    up=st.integers(0, 10**7),
    down=st.integers(0, 10**7),
    deadline=st.one_of(st.none(), st.floats(1e-3, 20)),
    reachable=st.sets(st.sampled_from(["cloud", "leader"])),
    links=st.dictionaries(st.sampled_from(["cloud", "leader"]), links_st),
    dvs=st.booleans(),
)
def test_policy_properties(name, cycles, up, down, deadline, reachable, links, dvs):
    task = Task(cycles, up, down, deadline)
    p = choose_placement(task, PROFILES[name], reachable=reachable, links=links, dvs=dvs)
    # never an unreachable tier
    assert p.tier == "local" or p.tier in reachable
    assert all(o["tier"] == "local" or o["tier"] in reachable for o in p.options)
    feasible = [o for o in p.options if o["meets_deadline"]]
    if feasible:
        assert not p.deadline_missed
        assert p.robot_energy_j == min(o["robot_energy_j"] for o in feasible)
        assert deadline is None or p.predicted_s <= deadline
    else:
        assert p.deadline_missed
        assert p.predicted_s == min(o["predicted_s"] for o in p.options)
