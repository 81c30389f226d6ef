"""Eq 3.18-3.19: transmission energy over a fading channel and its optimal bit schedule."""

from __future__ import annotations

import itertools
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.energy.transmission import (
    Channel,
    OptimalSchedule,
    equal_split_energy,
    lambda_from_eq44,
    schedule_known_gains,
    simulate,
    slot_energy,
)
from scmr_mesh.errors import InputError


def test_slot_energy_by_hand():
    # Eq 3.18: lambda s^n / g = 1e-6 * 1000^2 / 2 = 0.5 J
    assert slot_energy(1000, 2.0, lam=1e-6, order=2) == pytest.approx(0.5)
    assert slot_energy(0, 0.3, lam=1.0, order=3) == 0.0


def test_order_one_with_a_constant_channel_is_eq_4_4():
    # robot1: P_u * D / B_u = 83.54 * 8/23 = 29.057391 J for 1 MiB at 23 Mb/s
    lam = lambda_from_eq44(83.54, 3014656)
    assert slot_energy(8 * 1048576, 1.0, lam=lam, order=1) == pytest.approx(29.057391, abs=1e-6)
    # and no schedule can beat it on a channel that never fades
    opt = OptimalSchedule(slots=5, channel=Channel.constant(), order=1)
    assert opt.expected_energy(8 * 1048576, lam=lam) == pytest.approx(29.057391, abs=1e-6)


def test_two_slot_dp_by_hand():
    # gains 0.5 / 2 equally likely, n = 2: c1 = E[1/g] = 1.25,
    # c2 = E[1 / (g + 1/c1)] = 0.5/1.3 + 0.5/2.8 = 0.563187
    ch = Channel((0.5, 2.0), (0.5, 0.5))
    opt = OptimalSchedule(slots=2, channel=ch, order=2)
    assert opt.coeffs[0] == pytest.approx(1.25)
    assert opt.coeffs[1] == pytest.approx(0.5 / 1.3 + 0.5 / 2.8)
    # in a good slot send more than half, in a bad one less: s = b g / (g + 1/c1)
    assert opt.send_now(1000, 2, 2.0) == pytest.approx(1000 * 2 / 2.8)
    assert opt.send_now(1000, 2, 0.5) == pytest.approx(1000 * 0.5 / 1.3)
    assert opt.send_now(123, 1, 0.5) == 123  # the last slot sends what is left


def test_known_gains_closed_form_matches_a_grid_search():
    gains = [0.4, 1.7]
    s, e = schedule_known_gains(100.0, gains, lam=1.0, order=3)
    best = min((slot_energy(x, gains[0], lam=1.0, order=3) + slot_energy(100 - x, gains[1], lam=1.0, order=3), x)
               for x in [i / 100 for i in range(10001)])
    assert e == pytest.approx(best[0], rel=1e-6)
    assert s[0] == pytest.approx(best[1], abs=0.02)
    assert sum(s) == pytest.approx(100.0)


def test_dp_value_is_the_exact_expectation_of_the_policy():
    """Enumerate every gain sequence of a small channel: the policy's mean cost is lambda L^n c_T."""
    ch = Channel((0.3, 1.0, 2.5), (0.2, 0.5, 0.3))
    for n, slots in ((2, 3), (3, 2), (1, 3)):
        opt = OptimalSchedule(slots=slots, channel=ch, order=n)
        total = 0.0
        for seq in itertools.product(range(3), repeat=slots):
            p = 1.0
            for i in seq:
                p *= ch.probs[i]
            sent, e = simulate(opt, 50.0, [ch.gains[i] for i in seq], lam=0.01)
            assert sum(sent) == pytest.approx(50.0)
            total += p * e
        assert total == pytest.approx(opt.expected_energy(50.0, lam=0.01), rel=1e-9)


def test_optimal_is_between_the_clairvoyant_bound_and_the_equal_split():
    ch = Channel.rayleigh(states=16)
    rng = random.Random(7)
    opt = OptimalSchedule(slots=4, channel=ch, order=2)
    runs = 4000
    bound = causal = 0.0
    for _ in range(runs):
        g = [rng.choices(ch.gains, ch.probs)[0] for _ in range(4)]
        bound += schedule_known_gains(1.0, g, lam=1.0, order=2)[1] / runs
        causal += simulate(opt, 1.0, g, lam=1.0)[1] / runs
    assert bound < causal
    assert causal == pytest.approx(opt.expected_energy(1.0, lam=1.0), rel=0.1)  # Monte Carlo
    assert opt.expected_energy(1.0, lam=1.0) < equal_split_energy(1.0, 4, ch, lam=1.0, order=2)


@settings(max_examples=60, deadline=None)
@given(gains=st.lists(st.floats(0.05, 20), min_size=1, max_size=5),
       n=st.sampled_from([1.0, 1.5, 2.0, 3.0]), slots=st.integers(1, 6))
def test_more_slots_never_cost_more(gains, n, slots):
    ch = Channel(tuple(gains), tuple([1.0 / len(gains)] * len(gains)))
    opt = OptimalSchedule(slots=slots + 1, channel=ch, order=n)
    assert opt.coeffs[slots] <= opt.coeffs[slots - 1] * (1 + 1e-12)
    assert opt.expected_energy(10.0, lam=1.0) <= equal_split_energy(10.0, slots + 1, ch, lam=1.0, order=n) * (1 + 1e-9)


def test_rayleigh_discretisation_keeps_the_mean():
    ch = Channel.rayleigh(2.5, states=20)
    assert sum(g * p for g, p in zip(ch.gains, ch.probs)) == pytest.approx(2.5)
    assert list(ch.gains) == sorted(ch.gains)


@pytest.mark.parametrize("bad", [
    lambda: Channel((1.0,), (0.5,)),
    lambda: Channel((0.0,), (1.0,)),
    lambda: Channel((), ()),
    lambda: OptimalSchedule(slots=0, channel=Channel.constant()),
    lambda: OptimalSchedule(slots=2, channel=Channel.constant(), order=0.5),
    lambda: slot_energy(-1, 1.0, lam=1.0, order=2),
])
def test_bad_inputs_name_the_value(bad):
    with pytest.raises(InputError):
        bad()
