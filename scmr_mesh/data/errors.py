"""Errors of the data tier (all derive from :mod:`scmr_mesh.errors`)."""

from __future__ import annotations

from scmr_mesh.errors import InputError, ScmrError, WireError


class StoreError(InputError):
    """The operational data store file is missing, corrupt or of an unknown schema."""


class QueueError(ScmrError):
    """Root of the on-disk telemetry queue's failures."""


class QueueFullError(QueueError):
    """The queue holds ``max_bytes`` of unacknowledged records and refuses a new one.

    Nothing is dropped: the caller keeps the item (or slows down) and the queue
    counts the refusal in :attr:`QueueStats.refused`.
    """


class QueueWriteError(QueueError):
    """The file system refused an append (full, read-only, immutable, I/O error).

    The segment is left exactly as it was before the call (a partial write is
    truncated away), and the refusal is counted in :attr:`QueueStats.refused`.
    """


class QueueCorruptError(QueueError):
    """A segment file holds a record whose length or CRC does not check out."""


class TelemetryError(WireError):
    """A telemetry record or a data-tier message does not match its format."""


__all__ = [
    "QueueCorruptError",
    "QueueError",
    "QueueFullError",
    "QueueWriteError",
    "StoreError",
    "TelemetryError",
]
