"""Zenoh encodings of scmr payloads, so generic Zenoh tools can show them.

Every scmr message (request, reply, error, load, candidacy, telemetry, data-tier
messages) is a msgpack map: ``application/msgpack``; the per-request records on
``scmr/results/<robot>`` are JSON text: ``application/json`` (docs/protocol.md).
"""

from __future__ import annotations

import functools

from scmr_mesh import wire


@functools.cache
def msgpack():
    """``zenoh.Encoding("application/msgpack")`` (made once)."""
    import zenoh

    return zenoh.Encoding(wire.MSGPACK_ENCODING)


@functools.cache
def json():
    """``zenoh.Encoding("application/json")`` (made once)."""
    import zenoh

    return zenoh.Encoding(wire.JSON_ENCODING)
