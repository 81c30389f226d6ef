"""Fuzz the drivable queryable of a real ``scmr cloud`` process (real pipeline, 1 worker).

Hypothesis builds bad requests of several families: garbage bytes, msgpack that is not a
request, requests with a field removed / retyped / of the wrong version, and requests
whose image is truncated, random, a decompression bomb (a tiny PNG or JPEG whose header
claims 100000 x 100000 pixels), or raw bytes whose shape is absurd or does not match.
Each must get exactly one *error* reply that validates against schemas/error.schema.json,
with a code from the wire's list and a message naming the problem; and after each one
a good request from another robot is still served.  The cloud process must survive.

About 12 s (max_examples kept small: this is a smoke fuzz, not a campaign).
"""

from __future__ import annotations

import struct
import zlib

import msgpack
import pytest
from cloud_querier import ask, cloud_querier
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh import wire
from scmr_mesh.imaging.codec import MAX_PIXELS
from scmr_mesh.mesh.testing import synthetic_png

LIMIT = 2_000_000
BAD_CODES = {"malformed", "oversized", "wrong_version"}
FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz")
    with cloud_querier(tmp, "fz", "--workers", "1", "--max-request-bytes", str(LIMIT), "--ods", str(tmp / "ods.sqlite"),
                       requester="good", ready_timeout=60, lease_ms=500, query_timeout=10.0,
                       stopped="the cloud did not stop cleanly after the fuzzing") as (p, q):
        yield p, q


GOOD_PNG = synthetic_png(3)


def _good(seq: int = 0, **over) -> dict:
    return {**wire.make_request("good", seq, GOOD_PNG, encoding="png"), **over}


_seq = iter(range(10**9))


def _check_bad_then_good(cloud, payload: bytes, *, needles=(), allow_ok=False) -> dict | None:
    proc, q = cloud
    kind, msg = ask(q, payload)
    if kind == "ok":
        assert allow_ok, f"a bad request was served: {msg.get('robot')}/{msg.get('seq')}"
    else:
        assert msg["code"] in BAD_CODES, msg
        assert len(msg["message"]) > 10
        low = msg["message"].lower()
        assert any(n.lower() in low for n in needles) if needles else True, (needles, msg["message"])
    seq = next(_seq)
    kind2, rep = ask(q, wire.encode(_good(seq)))
    assert kind2 == "ok" and rep["seq"] == seq, "the service stopped serving good requests"
    assert proc.poll() is None
    return msg if kind == "err" else None


# ------------------------------------------------------------------ image builders
def _png(width: int, height: int, body: bytes = b"\x00" * 16, *, iend: bool = True) -> bytes:
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(body))
    return out + (chunk(b"IEND", b"") if iend else b"")


def _jpeg(width: int, height: int) -> bytes:
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + sof + b"\x00" * 32 + b"\xff\xd9"


# ------------------------------------------------------------------ strategies
any_value = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(allow_nan=True),
    st.text(max_size=20), st.binary(max_size=20),
    st.lists(st.integers(), max_size=4), st.dictionaries(st.text(max_size=4), st.integers(), max_size=3),
)
FIELDS = list(_good().keys())


@FUZZ
@given(blob=st.binary(max_size=3000))
def test_garbage_bytes(cloud, blob):
    _check_bad_then_good(cloud, blob, needles=("msgpack", "map", "kind", "version", "v"))


@FUZZ
@given(value=st.recursive(any_value, lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=3), c, max_size=3), max_leaves=8))
def test_msgpack_that_is_not_a_request(cloud, value):
    _check_bad_then_good(cloud, msgpack.packb(value, use_bin_type=True))


@FUZZ
@given(field=st.sampled_from(FIELDS), action=st.sampled_from(["drop", "retype"]), value=any_value)
def test_request_with_missing_or_mistyped_field(cloud, field, action, value):
    req = _good(0)
    if action == "drop":
        if field == "attempt":  # optional in the schema: a valid request
            return
        del req[field]
    else:
        req[field] = value
    msg = _check_bad_then_good(cloud, wire.encode(req), allow_ok=True,
                               needles=(field, "version", "kind", "image", "png", "jpeg", "decode"))
    if msg is None:  # served: the new value must have been a valid one
        wire.validate(req, "request")


@FUZZ
@given(v=st.integers(-5, 10**6).filter(lambda v: v != wire.WIRE_VERSION))
def test_wrong_schema_version(cloud, v):
    msg = _check_bad_then_good(cloud, wire.encode(_good(0, v=v)), needles=(str(v),))
    assert msg["code"] == "wrong_version"


@FUZZ
@given(cut=st.integers(1, len(GOOD_PNG) - 1))
def test_truncated_png(cloud, cut):
    msg = _check_bad_then_good(cloud, wire.encode(_good(0, image=GOOD_PNG[:cut])),
                               needles=("truncated", "corrupt", "png", "image"))
    assert msg["code"] == "malformed"


@FUZZ
@given(width=st.integers(1, 100_000), height=st.integers(1, 100_000),
       fmt=st.sampled_from(["png", "jpeg"]))
def test_bombs_and_absurd_dimensions(cloud, width, height, fmt):
    if fmt == "jpeg":  # JPEG sizes are 16-bit
        width, height = min(width, 65535), min(height, 65535)
    img = _png(width, height) if fmt == "png" else _jpeg(width, height)
    proc, q = cloud
    kind, msg = ask(q, wire.encode(_good(0, image=img, encoding=fmt)))
    if width * height > MAX_PIXELS:
        # refused from the header, before any pixel is decoded
        assert kind == "err" and msg["code"] == "malformed" and "pixels" in msg["message"], msg
    elif kind == "err":  # the body rarely matches the claimed size: corrupt
        assert msg["code"] == "malformed", msg
    else:  # a tiny image whose 16 zero bytes happen to be enough pixels: served
        assert width * (height * 3 + 1) <= 16 or width * height <= 16, (width, height)
    _check_bad_then_good(cloud, wire.encode(_good(0, image=b"x", encoding="png")), needles=("png", "image"))


def test_the_classic_bomb_is_refused_fast(cloud):
    """A 1 KB PNG claiming 100000 x 100000 RGB pixels (30 GB decoded)."""
    bomb = _png(100_000, 100_000, b"\x00" * 1000)
    assert len(bomb) < 200
    msg = _check_bad_then_good(cloud, wire.encode(_good(0, image=bomb)), needles=("100000x100000",))
    assert msg["code"] == "malformed"


@FUZZ
@given(h=st.integers(1, 16384), w=st.integers(1, 16384), n=st.integers(0, 5000))
def test_raw_with_wrong_or_absurd_shape(cloud, h, w, n):
    if h * w * 3 == n:
        return
    req = _good(0, encoding="raw", shape=[h, w, 3], image=b"\x07" * max(n, 1))
    msg = _check_bad_then_good(cloud, wire.encode(req), needles=("bytes", "pixels", "shape", "oversized"))
    assert msg["code"] in {"malformed", "oversized"}


def test_oversized_payload(cloud):
    msg = _check_bad_then_good(cloud, wire.encode(_good(0, image=b"\x00" * (LIMIT + 1))),
                               needles=(str(LIMIT),))
    assert msg["code"] == "oversized"


def test_deeply_nested_msgpack(cloud):
    _check_bad_then_good(cloud, b"\x91" * 200_000 + b"\x01", needles=("msgpack",))


def test_service_survives_a_dead_worker(cloud):
    """A worker killed (OOM killer, a crash in native code) must not end the service.

    Runs last in this module: it kills the cloud's only worker process."""
    import json
    import os
    import signal
    import time

    proc, q = cloud
    worker = json.loads(proc.ready_file.read_text())["workers"][0]
    os.kill(worker, signal.SIGKILL)

    def dead() -> bool:  # gone, or a zombie waiting for the pool to reap it
        try:
            with open(f"/proc/{worker}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] == "Z"
        except OSError:
            return True

    deadline = time.monotonic() + 30
    while not dead() and time.monotonic() < deadline:  # the condition, not a fixed sleep
        time.sleep(0.01)
    assert dead()
    outcomes = []
    for seq in range(3):
        kind, msg = ask(q, wire.encode(_good(10_000 + seq)))
        outcomes.append(kind if kind == "ok" else msg["code"])
    assert proc.poll() is None
    # at most the request caught in the crash fails (as "internal"); then it serves again
    assert outcomes[-1] == "ok" and set(outcomes) <= {"ok", "internal"}, outcomes
