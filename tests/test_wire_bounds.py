"""Another node's message is untrusted input: wire.decode refuses NaN, inf, huge or
fake integers and oversized control messages, counts them, and never lets them
through (issue 28, probes 1, 2 and the NaN part of 7)."""

from __future__ import annotations

import logging
import math

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh import wire
from scmr_mesh.errors import ConfigError
from scmr_mesh.scenario.spec import parse_scenario


def _cand(**over) -> dict:
    msg = wire.make_candidate("r1", term=3, leading=False, clock_hz=1.5e9, power_w=6.0, battery=0.9, load=0.5,
                              capability="pi4")
    msg.update(over)
    return msg


def _raw(msg: dict) -> bytes:
    return msgpack.packb(msg, use_bin_type=True)


def test_a_good_candidacy_and_load_decode():
    assert wire.decode(_raw(_cand()), kind="candidate")["term"] == 3
    load = wire.make_load("c1", "cloud", workers=2, inflight=1, served=9, clock_hz=3e9, power_w=65.0)
    assert wire.decode(_raw(load), kind="load")["clock_hz"] == 3e9
    assert wire.decode(_raw(_cand(term=wire.MAX_TERM)), kind="candidate")["term"] == wire.MAX_TERM


BAD_CANDIDACIES = [
    ("clock_hz", math.inf), ("clock_hz", -math.inf), ("clock_hz", math.nan), ("clock_hz", 1e300),
    ("load", math.inf), ("load", math.nan), ("battery", math.nan), ("battery", math.inf),
    ("power_w", math.inf), ("power_w", math.nan),
    ("term", 2**64 - 1), ("term", 2**63), ("term", wire.MAX_TERM + 1), ("term", 1e300), ("term", 3.0),
    ("term", -1), ("term", math.nan), ("since_unix_ns", 1e300), ("t_unix_ns", math.inf), ("t_unix_ns", -5),
]


@pytest.mark.parametrize("field,value", BAD_CANDIDACIES, ids=[f"{f}={v!r}" for f, v in BAD_CANDIDACIES])
def test_bad_candidacy_numbers_are_refused_naming_the_field(field, value):
    before = wire.rejected().get("candidate", {}).get("malformed", 0)
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(_raw(_cand(**{field: value})), kind="candidate")
    assert ei.value.code == "malformed" and field in str(ei.value)
    assert wire.rejected()["candidate"]["malformed"] == before + 1


@pytest.mark.parametrize("field,value", [("clock_hz", math.inf), ("clock_hz", math.nan), ("power_w", math.inf),
                                         ("workers", 1e300), ("inflight", 2**64 - 1), ("served", math.nan)])
def test_bad_load_numbers_are_refused(field, value):
    msg = wire.make_load("c1", "cloud", workers=2, inflight=1, served=9)
    msg[field] = value
    with pytest.raises(wire.WireProblem, match=field):
        wire.decode(_raw(msg), kind="load")


@pytest.mark.parametrize("where", ["battery", "pose", "results", "seq"])
def test_bad_telemetry_numbers_are_refused(where):
    msg = wire.make_telemetry("r1", 5, pose={"x": 1.0, "y": 2.0, "theta": 0.5}, battery=0.8, health="ok",
                              results={"requests": 3, "succeeded": 2, "by_tier": {}, "last_tor_ms": None})
    if where == "pose":
        msg["pose"]["x"] = math.nan
    elif where == "results":
        msg["results"]["last_tor_ms"] = math.inf
    elif where == "seq":
        msg["seq"] = 1e300
    else:
        msg["battery"] = math.nan
    with pytest.raises(wire.WireProblem, match=where):
        wire.decode(_raw(msg), kind="telemetry")


def test_a_request_with_a_nan_deadline_or_float_seq_gets_malformed():
    req = wire.make_request("r1", 7, b"\x89PNG....")
    for field, value in (("deadline_ms", math.nan), ("seq", 1e300), ("seq", 2**64 - 1)):
        with pytest.raises(wire.WireProblem) as ei:
            wire.decode(_raw({**req, field: value}), kind="request", max_bytes=wire.MAX_REQUEST_BYTES)
        assert ei.value.code == "malformed" and field in str(ei.value)


def test_an_8_mb_candidacy_is_refused_before_parsing():
    big = _raw(_cand(capability="x" * (8 << 20)))
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(big, kind="candidate")
    assert ei.value.code == "oversized" and ei.value.partial is None
    with pytest.raises(wire.WireProblem, match="oversized|exceeds"):
        wire.decode(_raw({**wire.make_load("c", "cloud", workers=1, inflight=0, served=0), "pad": b"x" * 5000}),
                    kind="load")


def test_refusals_warn_at_most_once_per_kind_per_period(caplog, monkeypatch):
    monkeypatch.setattr(wire, "_LAST_WARNING", {})
    with caplog.at_level(logging.WARNING, logger="scmr_mesh.wire"):
        for _ in range(50):
            with pytest.raises(wire.WireProblem):
                wire.decode(_raw(_cand(clock_hz=math.inf)), kind="candidate")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "clock_hz" in warnings[0].getMessage()


def test_the_next_term_of_the_largest_accepted_term_still_encodes():
    top = wire.decode(_raw(_cand(term=wire.MAX_TERM)), kind="candidate")["term"]
    claim = wire.make_candidate("r2", term=top + 1, leading=True, clock_hz=1e9, power_w=None, battery=1.0, load=0.0)
    # publishing never fails any more (msgpack took 2**63 - 1 + 1 as an error); peers refuse the
    # claim beyond MAX_TERM, the residual term-exhaustion attack docs/SECURITY.md describes
    assert msgpack.unpackb(wire.encode(claim))["term"] == wire.MAX_TERM + 1
    with pytest.raises(wire.WireProblem, match="term"):
        wire.decode(wire.encode(claim), kind="candidate")


numbers = (st.integers(-(2**63), 2**64 - 1)  # what msgpack can carry
            | st.floats(allow_nan=True, allow_infinity=True)
           | st.sampled_from([math.nan, math.inf, -math.inf, 1e300, 2**64 - 1, 2**53 + 1, -1, 0, 0.5, 1.0]))
FIELDS = ("term", "since_unix_ns", "clock_hz", "power_w", "battery", "load", "t_unix_ns")


def _numbers_in(value):
    if isinstance(value, dict):
        for v in value.values():
            yield from _numbers_in(v)
    elif isinstance(value, list):
        for v in value:
            yield from _numbers_in(v)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield value


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(FIELDS), numbers, min_size=1, max_size=4))
def test_whatever_decodes_has_only_finite_bounded_numbers(over):
    try:
        msg = wire.decode(_raw(_cand(**over)), kind="candidate")
    except wire.WireProblem:
        return
    for x in _numbers_in(msg):
        assert math.isfinite(x) and abs(x) <= wire.MAX_WIRE_INT
    assert isinstance(msg["term"], int) and 0 <= msg["term"] <= wire.MAX_TERM
    assert isinstance(msg["t_unix_ns"], int)
    assert 0 < msg["clock_hz"] <= 1e12 and 0 <= msg["battery"] <= 1 and 0 <= msg["load"] <= 1e6


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["load", "telemetry"]), numbers, st.sampled_from(["workers", "inflight", "served",
                                                                         "clock_hz", "power_w", "seq", "battery"]))
def test_load_and_telemetry_decode_only_sane_numbers(kind, value, field):
    if kind == "load":
        msg = wire.make_load("c1", "cloud", workers=2, inflight=1, served=9, clock_hz=2e9, power_w=10.0)
    else:
        msg = wire.make_telemetry("r1", 5, pose={"x": 1.0, "y": 2.0, "theta": 0.5}, battery=0.8, health="ok",
                                  results={"requests": 3, "succeeded": 2, "by_tier": {}, "last_tor_ms": None})
    msg[field] = value
    try:
        out = wire.decode(_raw(msg), kind=kind)
    except wire.WireProblem:
        return
    for x in _numbers_in(out):
        assert math.isfinite(x) and abs(x) <= wire.MAX_WIRE_INT


# ------------------------------------------------------------- scenario files
def _scenario(**fault) -> dict:
    return {"name": "t", "seed": 1, "duration_s": 5, "fleet": {"robots": [{"id": "robot1"}]},
            "faults": [{"kind": "crash", "at_s": 1, "peer": "cloud", **fault}]}


@pytest.mark.parametrize("field,value", [("at_s", math.nan), ("at_s", math.inf), ("for_s", math.nan)])
def test_scenario_nan_and_inf_are_one_line_config_errors(field, value):
    with pytest.raises(ConfigError) as ei:
        parse_scenario(_scenario(**{field: value}), source="bad.toml")
    text = str(ei.value)
    assert "\n" not in text and f"faults[0].{field}" in text and "finite" in text


def test_scenario_nan_duration_is_refused():
    with pytest.raises(ConfigError, match="duration_s.*finite"):
        parse_scenario({**_scenario(), "duration_s": math.nan}, source="bad.toml")
