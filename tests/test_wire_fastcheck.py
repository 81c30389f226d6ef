"""The fast schema check (scmr_mesh/_schema.py) answers as jsonschema does.

jsonschema is the reference: for every wire kind, valid messages and
mutations of them (wrong types, bools for numbers, 1.0 for integers, missing
and extra fields, out-of-range values) get the same yes/no from both.
"""

from __future__ import annotations

import sys
import subprocess

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh import _schema, wire

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**64, 2**64) | st.floats(allow_nan=False)
    | st.sampled_from([0, 1, 1.0, 2.5, -1, 3, 225, 300, 16385, True, False, "raw", "png", "best", "cloud",
                       "request", "reply", "error", "telemetry", "load", "r1", "bad name!", "", b"", b"x",
                       b"\x89PNG\r\n\x1a\n"])
    | st.text(max_size=8) | st.binary(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)


def _samples() -> dict[str, dict]:
    req = wire.make_request("r1", 3, b"\x89PNG....", encoding="png", deadline_ms=500.0)
    raw = wire.make_request("r1", 4, b"\x00" * 12, encoding="raw", shape=(2, 2, 3))
    rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n", shape=(225, 300), threshold=7,
                          timings_ms={"srm": 1.5}, served_by="c1", tier="cloud", server_ms=3.0, queue_ms=0.5)
    err = wire.make_error("busy", "later", served_by="c1", tier="cloud", request=req, retry_after_ms=50.0)
    load = wire.make_load("c1", "cloud", workers=2, inflight=1, served=9)
    tel = wire.make_telemetry("r1", 5, pose={"x": 1.0, "y": 2.0, "theta": 0.5}, battery=0.8, health="ok",
                              results={"requests": 3, "succeeded": 2, "by_tier": {"cloud": 2}, "last_tor_ms": None})
    return {"request": req, "request_raw": raw, "reply": rep, "error": err, "load": load, "telemetry": tel}


SAMPLES = _samples()


def _reference(kind: str):
    return wire.validator(kind)


@pytest.mark.parametrize("kind", wire.KINDS)
def test_every_wire_schema_compiles(kind):
    assert wire.fast_check(kind) is not None


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_samples_are_valid_for_both(name):
    kind = SAMPLES[name]["kind"]
    assert wire.fast_check(kind)(SAMPLES[name]) and _reference(kind).is_valid(SAMPLES[name])


@given(name=st.sampled_from(sorted(SAMPLES)), data=st.data())
@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_mutated_messages_get_the_same_answer(name, data):
    msg = dict(SAMPLES[name])
    kind = msg["kind"]
    for _ in range(data.draw(st.integers(1, 3))):
        op = data.draw(st.sampled_from(["set", "drop", "add", "nest"]))
        field = data.draw(st.sampled_from(sorted(msg) or ["v"]))
        if op == "set":
            msg[field] = data.draw(json_values)
        elif op == "drop":
            msg.pop(field, None)
        elif op == "add":
            msg[data.draw(st.text(max_size=6))] = data.draw(json_values)
        elif isinstance(msg.get(field), list) and msg[field]:
            lst = list(msg[field])
            lst[data.draw(st.integers(0, len(lst) - 1))] = data.draw(json_values)
            msg[field] = lst
        elif isinstance(msg.get(field), dict):
            msg[field] = dict(msg[field], **{data.draw(st.text(max_size=4)): data.draw(json_values)})
    assert wire.fast_check(kind)(msg) == _reference(kind).is_valid(msg), msg


@given(st.sampled_from(wire.KINDS), json_values)
@settings(max_examples=300, deadline=None)
def test_any_value_gets_the_same_answer(kind, value):
    assert wire.fast_check(kind)(value) == _reference(kind).is_valid(value)


@pytest.mark.parametrize("schema, good, bad", [
    ({"type": "integer"}, [1, 1.0, -3], [True, 1.5, "1", None]),
    ({"const": 1}, [1, 1.0], [True, "1"]),
    ({"enum": [False, "a"]}, [False, "a"], [0, "b"]),
    ({"exclusiveMinimum": 0}, [0.1, "x"], [0, -1]),
    ({"type": "array", "prefixItems": [{"const": 3}], "items": {"type": "string"}}, [[3], [3, "a"]], [[4], [3, 1]]),
    ({"oneOf": [{"type": "integer"}, {"type": "number"}]}, [1.5], [1]),
    ({"if": {"const": 1}, "then": {"type": "integer"}, "else": {"type": "string"}}, [1, "x"], [2]),
    ({"not": {"type": "null"}}, [0], [None]),
    ({"x-bytes": {"minLength": 2, "maxLength": 3}}, [b"ab", bytearray(b"abc")], [b"a", b"abcd", "ab"]),
])
def test_keywords_match_the_reference(schema, good, bad):
    import jsonschema

    cls = jsonschema.validators.extend(jsonschema.Draft202012Validator, validators={"x-bytes": wire._bytes_keyword})
    check = _schema.compile_check(schema)
    for v in good:
        assert check(v) and cls(schema).is_valid(v), v
    for v in bad:
        assert not check(v) and not cls(schema).is_valid(v), v


def test_unknown_keyword_is_refused_not_ignored():
    with pytest.raises(_schema.Unsupported, match=r"\$ref"):
        _schema.compile_check({"properties": {"a": {"$ref": "#/x"}}})


def test_a_bad_message_is_still_explained_by_jsonschema():
    bad = dict(SAMPLES["request"], priority=-1)
    with pytest.raises(wire.WireProblem) as ei:
        wire.validate(bad, "request")
    assert ei.value.code == "malformed" and "priority" in str(ei.value)


def test_good_messages_do_not_import_jsonschema():
    code = ("import sys\nfrom scmr_mesh import wire\nwire.warm()\n"
            "r = wire.make_request('r1', 1, b'x', encoding='png')\n"
            "wire.decode(wire.encode(r), kind='request')\nprint('jsonschema' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stdout + r.stderr
