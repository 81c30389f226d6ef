"""Small helpers for the Zenoh resources peers own: undeclare them all, read a liveliness sample.

Liveliness is compared by :class:`zenoh.SampleKind` (zenoh-python's
``examples/z_sub_liveliness.py`` shape), never by the sample kind's string.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["appeared", "undeclare_all"]


def appeared(sample: Any) -> bool:
    """True when a liveliness sample says its token appeared (``PUT``), False when it went (``DELETE``)."""
    import zenoh

    return sample.kind == zenoh.SampleKind.PUT


def undeclare_all(objs: Iterable[Any]) -> None:
    """Undeclare every declared Zenoh object in ``objs`` (None skipped); never raises (a closing session)."""
    for obj in objs:
        if obj is None:
            continue
        try:
            obj.undeclare()
        except Exception as exc:  # the session is closing or closed
            log.debug("undeclare %r: %s", obj, exc)
