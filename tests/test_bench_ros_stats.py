"""``scmr bench ros``'s figures from its rounds: the paired differences, the median's interval, the verdict."""

from __future__ import annotations

import doctest
import itertools
import statistics

import pytest
from hypothesis import given
from hypothesis import strategies as st

from scmr_mesh.bench import ros


def test_the_module_s_examples_hold():
    failed, tried = doctest.testmod(ros, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert tried >= 5 and failed == 0


def test_rounds_pair_each_bridge_block_with_its_own_robot_block():
    # round 1's bridge frames are slow and so is its robot block: the load cancels in the pair
    names = [["a1", "a2", "a3"], ["b1", "b2", "b3"]]
    e2e = {"a1": 30.0, "a2": 31.0, "a3": 32.0, "b1": 11.0, "b2": 12.0, "b3": 13.0}
    rtor = [[29.0, 29.5, 30.0], [10.0, 10.0, 10.5]]
    out = ros.added_vs_robot(names, e2e, rtor)
    assert out["added_vs_robot_rounds_ms"] == [1.5, 2.0]
    assert out["added_vs_robot_ms"] == 1.75
    assert out["added_vs_robot_interval_ms"] is None  # two rounds: no 95 % interval
    # a round whose masks all got lost is listed as None and left out of the median
    e2e_lost = {k: v for k, v in e2e.items() if not k.startswith("b")}
    out = ros.added_vs_robot(names, e2e_lost, rtor)
    assert out["added_vs_robot_rounds_ms"] == [1.5, None] and out["added_vs_robot_ms"] == 1.5


def _coverage(n: int, k: int) -> float:
    """P(x_(k) <= median < x_(n+1-k)) by counting: how many of the 2**n sign patterns put at least
    k draws below the median and at least k above it."""
    hits = sum(1 for signs in itertools.product((0, 1), repeat=n) if k <= sum(signs) <= n - k)
    return hits / 2 ** n


@pytest.mark.parametrize("n", range(1, 15))
def test_the_interval_s_coverage_is_the_binomial_count_and_the_widest_k_above_the_level(n):
    got = ros.median_interval([float(i) for i in range(n)])
    ks = [k for k in range(1, n // 2 + 1) if _coverage(n, k) >= 0.95]
    if not ks:
        assert got is None
        return
    k = max(ks)
    assert got == (float(k - 1), float(n - k), round(_coverage(n, k), 3))


@given(st.lists(st.floats(-50, 50, allow_nan=False), min_size=6, max_size=40))
def test_the_interval_holds_the_median_and_comes_from_the_data(xs):
    lo, hi, level = ros.median_interval(xs)
    med = statistics.median(xs)
    assert lo <= round(med, 2) + 1e-9 and round(med, 2) - 1e-9 <= hi
    assert level >= 0.95
    assert any(abs(lo - round(x, 2)) < 1e-9 for x in xs) and any(abs(hi - round(x, 2)) < 1e-9 for x in xs)


def _res(median, rounds, interval, level=0.961):
    return {"added_vs_robot_ms": median, "added_vs_robot_rounds_ms": rounds,
            "added_vs_robot_interval_ms": interval, "added_vs_robot_interval_level": level}


def test_the_verdict_is_met_only_when_the_whole_interval_is_within_the_limit():
    assert ros.target_line(_res(1.1, [1.0] * 9, [0.5, 1.9])).endswith("the <= 2 ms target is met")
    assert ros.target_line(_res(1.1, [1.0] * 9, [0.5, 2.0])).endswith("the <= 2 ms target is met")
    assert ros.target_line(_res(3.0, [1.0] * 9, [2.1, 3.9])).endswith("the <= 2 ms target is not met")
    undecided = ros.target_line(_res(1.9, [1.0] * 9, [0.8, 3.27]))
    assert "undecided against the <= 2 ms target" in undecided  # a median under the limit is not enough
    few = ros.target_line(_res(1.2, [1.0, None, 1.4], None, None))
    assert "median of 2 rounds" in few and "not judged" in few
    assert ros.target_line({"added_vs_robot_ms": None}) is None
