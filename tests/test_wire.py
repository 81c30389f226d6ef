"""Wire messages: round trips, schema rejection, versioning (pure; < 5 s)."""

from __future__ import annotations

import json

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh import keys, wire
from scmr_mesh.errors import InputError, WireError

names = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True)
requests = st.builds(
    wire.make_request,
    names,
    st.integers(0, 2**62),
    st.binary(min_size=1, max_size=2048),
    encoding=st.sampled_from(["png", "jpeg"]),
    priority=st.integers(0, 1_000_000),
    mode=st.sampled_from(wire.MODES),
    sent_unix_ns=st.integers(0, 2**63 - 1),
    attempt=st.integers(0, 10),
)


@given(requests)
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_request_round_trip(req):
    assert wire.decode(wire.encode(req), kind="request") == req


@given(st.integers(1, 4000), st.integers(1, 4000), st.binary(min_size=1, max_size=64))
@settings(deadline=None)  # a loaded 2-core box took over 200 ms for one example
def test_raw_request_needs_shape(h, w, data):
    req = wire.make_request("r", 0, data, encoding="raw", shape=(h, w, 3))
    assert wire.decode(wire.encode(req), kind="request")["shape"] == [h, w, 3]
    bad = dict(req, shape=None)
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(wire.encode(bad), kind="request")
    assert ei.value.code == "malformed" and "shape" in str(ei.value)


@given(
    st.binary(min_size=8, max_size=512),
    st.integers(-1, 256),
    st.dictionaries(st.text(min_size=1, max_size=12), st.floats(0, 1e6), max_size=8),
    st.sampled_from(keys.TIERS),
    st.floats(0, 1e5),
)
def test_reply_round_trip(png, thr, timings, tier, server_ms):
    req = wire.make_request("r1", 5, b"x")
    rep = wire.make_reply(req, mask_png=png, shape=(225, 300), threshold=thr, timings_ms=timings,
                          served_by="c1", tier=tier, server_ms=server_ms)
    out = wire.decode(wire.encode(rep), kind="reply")
    assert out == rep and out["seq"] == 5 and out["robot"] == "r1"


@given(st.sampled_from(wire.ERROR_CODES), st.text(max_size=3000), st.one_of(st.none(), requests))
def test_error_round_trip(code, message, req):
    err = wire.make_error(code, message, served_by="L", tier="leader", request=req)
    out = wire.decode(wire.encode(err), kind="error")
    assert out["code"] == code and len(out["message"]) <= 2000
    assert out["seq"] == (req["seq"] if req else None)


def test_telemetry_and_load_round_trip():
    t = wire.make_telemetry("r1", 3, pose={"x": 1, "y": 2, "theta": 0.5}, battery=1.7, health="ok",
                            results={"requests": 4, "succeeded": 4, "by_tier": {"cloud": 4}})
    assert wire.decode(wire.encode(t), kind="telemetry")["battery"] == 1.0  # clamped
    ld = wire.make_load("c1", "cloud", workers=2, inflight=3, served=10)
    assert wire.decode(wire.encode(ld), kind="load") == ld


# Mutations that the schema must reject, each with the field the message must name.
MUTATIONS = [
    (lambda r: r.pop("robot"), "robot"),
    (lambda r: r.update(seq=-1), "seq"),
    (lambda r: r.update(seq=True), "seq"),
    (lambda r: r.update(seq="7"), "seq"),
    (lambda r: r.update(robot="a/b"), "robot"),
    (lambda r: r.update(robot=""), "robot"),
    (lambda r: r.update(encoding="gif"), "encoding"),
    (lambda r: r.update(image=b""), "image"),
    (lambda r: r.update(image="text"), "image"),
    (lambda r: r.update(mode="fast"), "mode"),
    (lambda r: r.update(priority=-3), "priority"),
    (lambda r: r.update(shape=[10, 10, 4]), "shape"),
    (lambda r: r.update(extra=1), "extra"),
    (lambda r: r.update(kind="reply"), "kind"),
]


@pytest.mark.parametrize("mutate,field", MUTATIONS)
def test_schema_rejects_bad_requests(mutate, field):
    req = wire.make_request("r1", 1, b"\x89PNG")
    mutate(req)
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(wire.encode(req), kind="request")
    assert ei.value.code == "malformed"
    assert field in str(ei.value)


@given(st.binary(max_size=200))
def test_random_bytes_never_crash(data):
    try:
        wire.decode(data, kind="request")
    except wire.WireProblem as exc:
        assert exc.code in ("malformed", "wrong_version")


@given(st.integers(-(2**63), 2**63 - 1).filter(lambda v: v != wire.WIRE_VERSION))
def test_wrong_version_is_named(v):
    req = dict(wire.make_request("r1", 1, b"x"), v=v)
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(wire.encode(req), kind="request")
    assert ei.value.code == "wrong_version" and str(v) in str(ei.value)


def test_oversized_checked_before_parsing():
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(b"\x00" * 101, kind="request", max_bytes=100)
    assert ei.value.code == "oversized" and "101" in str(ei.value) and "100" in str(ei.value)
    assert isinstance(ei.value, WireError)


def test_schemas_are_valid_json_schema_files(repo_root):
    from jsonschema import Draft202012Validator

    for kind in wire.KINDS:
        schema = json.loads((repo_root / "schemas" / f"{kind}.schema.json").read_text())
        Draft202012Validator.check_schema(schema)
        assert set(schema["required"]) <= set(schema["properties"])


def test_factories_produce_every_required_field():
    req = wire.make_request("r", 0, b"x")
    assert set(wire.load_schema("request")["required"]) <= set(req)
    err = wire.make_error("busy", "m", served_by="c", tier="cloud")
    assert set(wire.load_schema("error")["required"]) <= set(err)
    with pytest.raises(ValueError):
        wire.make_error("nope", "m", served_by="c", tier="cloud")


def test_msgpack_bin_and_str_are_distinct():
    # a str image must not pass for bytes (use_bin_type keeps them apart)
    raw = msgpack.packb(dict(wire.make_request("r", 0, b"x"), image="x"), use_bin_type=True)
    with pytest.raises(wire.WireProblem):
        wire.decode(raw, kind="request")


# ------------------------------------------------------------------ keys
def test_keys_catalog():
    assert keys.drivable("cloud", "c1") == "scmr/drivable/cloud/c1"
    assert keys.drivable_request("cloud", "c1", "r1") == "scmr/drivable/cloud/c1/r1"
    assert keys.drivable_serve("cloud", "c1") == "scmr/drivable/cloud/c1/*"
    assert keys.drivable("leader", "L") == "scmr/drivable/leader/L"
    assert keys.alive("cloud", "c1") != keys.alive("leader", "c1")
    assert keys.parse(keys.alive("leader", "L")) == ("alive", "leader", "L")
    assert keys.telemetry("r1") == "scmr/telemetry/r1"
    assert keys.load("cloud", "c2") == "scmr/load/cloud/c2"


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "x" * 65, "a b", "$x", "q?"])
def test_keys_reject_bad_names(bad):
    with pytest.raises(InputError) as ei:
        keys.drivable("cloud", bad)
    assert repr(bad) in str(ei.value)


def test_keys_reject_unknown_tier():
    with pytest.raises(InputError, match="tier"):
        keys.drivable("edge", "n")


def test_a_schema_violation_keeps_what_was_readable_and_names_the_fix():
    """Issue #12, item 7."""
    bad = wire.encode({**wire.make_request("r7", 42, b"x"), "mode": "fast"})
    with pytest.raises(wire.WireProblem) as ei:
        wire.decode(bad, kind="request")
    assert ei.value.code == "malformed" and "schemas/request.schema.json" in str(ei.value)
    err = wire.make_error("malformed", str(ei.value), served_by="c", tier="cloud", request=ei.value.partial)
    assert (err["robot"], err["seq"]) == ("r7", 42)
    wire.validate(err, "error")
    with pytest.raises(wire.WireProblem, match=r"payload of 4 bytes is not msgpack \(it starts with 0xc1c1c1c1"):
        wire.decode(b"\xc1" * 4, kind="request")
    with pytest.raises(wire.WireProblem, match=r"msgpack list .*make_request"):
        wire.decode(wire.encode([1, 2]), kind="request")
    junk = wire.make_error("malformed", "m", served_by="c", tier="cloud", request={"robot": "x" * 65, "seq": -1})
    assert (junk["robot"], junk["seq"]) == (None, None)


@given(st.one_of(st.none(), st.floats(-2, 3, allow_nan=False)),
       st.one_of(st.none(), st.sampled_from(["seed not ground", "seed reaches the horizon", "dim seed"])))
def test_reply_confidence_and_abstained_round_trip(confidence, abstained):
    """Issue 27: the optional fields travel when given (confidence clamped to [0, 1]) and are absent otherwise."""
    req = wire.make_request("r1", 5, b"x")
    rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n", shape=(225, 300), threshold=7, timings_ms={},
                          served_by="c1", tier="cloud", server_ms=1.0, confidence=confidence, abstained=abstained)
    out = wire.decode(wire.encode(rep), kind="reply")
    assert out == rep
    assert ("confidence" in out) == (confidence is not None) and ("abstained" in out) == (abstained is not None)
    if confidence is not None:
        assert 0.0 <= out["confidence"] <= 1.0


def test_reply_with_confidence_out_of_range_is_refused():
    req = wire.make_request("r1", 5, b"x")
    rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n", shape=(225, 300), threshold=7, timings_ms={},
                          served_by="c1", tier="cloud", server_ms=1.0)
    assert "confidence" not in rep and "abstained" not in rep  # an older reader's reply
    wire.decode(wire.encode(rep), kind="reply")
    with pytest.raises(wire.WireProblem):
        wire.decode(wire.encode({**rep, "confidence": 1.5}), kind="reply")
    with pytest.raises(wire.WireProblem):
        wire.decode(wire.encode({**rep, "abstained": 3}), kind="reply")


# ----------------------------------------------- a reply answers its request (issue 25 item 8)
def _answer(req, **over):
    rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n", shape=(225, 300), threshold=7, timings_ms={},
                          served_by="c1", tier="cloud", server_ms=1.0)
    rep.update(over)
    return wire.decode(wire.encode(rep), kind="reply")


def test_a_reply_echoes_the_requests_robot_seq_and_frame_digest():
    req = wire.make_request("r1", 5, b"frame five", encoding="jpeg")
    assert req["digest"] == wire.frame_digest(b"frame five") and len(req["digest"]) == wire.DIGEST_BYTES
    wire.decode(wire.encode(req), kind="request")
    rep = _answer(req)
    assert (rep["robot"], rep["seq"], rep["digest"]) == ("r1", 5, req["digest"])
    assert wire.reply_mismatch(req, rep) is None
    err = wire.make_error("busy", "later", served_by="c1", tier="cloud", request=req)
    assert wire.decode(wire.encode(err), kind="error")["digest"] == req["digest"]


@pytest.mark.parametrize("why,make", [
    ("frame 1005", lambda req: _answer(wire.make_request("r1", 1005, b"frame five"))),  # seq off by 1,000
    ("another frame", lambda req: _answer(wire.make_request("r1", 5, b"last run's frame five"))),  # a replay
    ("robot 'r2'", lambda req: _answer(wire.make_request("r2", 5, b"frame five"))),
    ("no frame digest", lambda req: _answer({k: v for k, v in req.items() if k != "digest"})),  # an old server
    ("another frame", lambda req: _answer(req, digest=b"\0" * wire.DIGEST_BYTES)),
])
def test_a_reply_to_anything_else_does_not_match(why, make):
    req = wire.make_request("r1", 5, b"frame five", encoding="jpeg")
    got = wire.reply_mismatch(req, make(req))
    assert got is not None and why in got, got


def test_a_digest_of_the_wrong_size_is_refused():
    req = wire.make_request("r1", 5, b"x")
    with pytest.raises(wire.WireProblem, match="digest"):
        wire.decode(wire.encode({**req, "digest": b"\1" * 15}), kind="request")
    with pytest.raises(wire.WireProblem, match="digest"):
        wire.decode(wire.encode({**_answer(req), "digest": b"\1" * 17}), kind="reply")
