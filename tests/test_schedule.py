"""Periodic schedules from integers (frame k due at t0 + k x period): the robot's send loop and the benches."""

from __future__ import annotations

import itertools

import pytest

from scmr_mesh.qos.schedule import NS, Schedule, due_ns

from hypothesis import given, strategies as st


def frames_in_window(t0_ns: int, rate_hz: float, duration_s: float) -> list[int]:
    """Due times a sender that is never late sends in the window (an ideal clock)."""
    s = Schedule(t0_ns, rate_hz, duration_s)
    sent = []
    while not s.ended(s.next_due_ns()):
        now = s.next_due_ns()
        sent.append(now)
        s.advance(now)
    return sent


def test_five_hz_for_one_second_is_five_frames_even_near_240_s():
    """The flake of stop 19: t0 near 240 s, the float sum put the sixth due time under 1.0 s."""
    for t0 in (0, 240 * NS + 123_456_789, 10**6 * NS + 1):
        sent = frames_in_window(t0, 5.0, 1.0)
        assert [t - t0 for t in sent] == [0, 200_000_000, 400_000_000, 600_000_000, 800_000_000]


def test_the_float_running_sum_is_what_failed():
    """Accumulating 0.2 onto a monotonic value near 240 s lands under t0 + 1.0: the cause, shown."""
    t0 = 240.123456789
    t = t0
    for _ in range(5):
        t += 0.2
    assert t - t0 < 1.0  # the old loop's sixth frame was due 'before' the end
    assert due_ns(round(t0 * NS), 5, 5.0) - round(t0 * NS) == NS  # the integer schedule is exact


def test_three_hz_for_one_second_is_three_frames():
    assert len(frames_in_window(7, 3.0, 1.0)) == 3


def test_a_late_sender_skips_missed_slots_instead_of_bursting():
    s = Schedule(0, 10.0)
    s.advance(0)
    s.advance(int(1.05 * NS))  # stalled 1 s after slot 1
    assert s.slot == 10  # due 1.0 s, at most one period late; not slots 2..9 in a burst
    assert s.next_due_ns() == NS


def test_ended_counts_the_time_the_frame_would_go_out():
    s = Schedule(0, 5.0, 1.0, slot=4)  # due 0.8 s
    assert not s.ended(int(0.8 * NS))
    assert s.ended(NS)  # overslept to the end: not sent
    assert Schedule(0, 5.0, None, slot=10**6).ended(10**18) is False


def test_no_rate_sends_back_to_back_until_the_end():
    s = Schedule(0, 0.0, 1.0)
    assert s.next_due_ns() == 0 and not s.ended(NS - 1) and s.ended(NS)


def test_a_negative_slot_is_refused():
    with pytest.raises(ValueError):
        due_ns(0, -1, 5.0)


@given(st.integers(0, 10**15), st.floats(0.1, 100), st.floats(0.01, 10))
def test_no_frame_at_or_after_the_end_and_none_missing(t0, rate, duration):
    sent = frames_in_window(t0, rate, duration)
    end = t0 + round(duration * NS)
    assert all(t0 <= t < end for t in sent)
    assert sent == sorted(set(sent))
    # every slot whose due time is inside the window was sent
    n_due = sum(1 for _ in itertools.takewhile(lambda k: due_ns(t0, k, rate) < end, itertools.count()))
    assert len(sent) == n_due
