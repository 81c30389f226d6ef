"""The data tier: operational data store, on-disk telemetry queue, data buffer, reports.

Pure (no Zenoh; the mesh glue is :mod:`scmr_mesh.mesh.data_service`).  Public names are
re-exported here and loaded on first use, so ``import scmr_mesh.data`` stays cheap::

    from scmr_mesh.data import OperationalDataStore, TelemetryQueue, DataBuffer, telemetry_report

See docs/DATA.md.
"""

from __future__ import annotations

from scmr_mesh._lazy import lazy_exports

_EXPORTS: dict[str, str] = {
    "OperationalDataStore": "ods", "InsertResult": "ods", "default_db_path": "ods",
    "TelemetryQueue": "queue", "QueueStats": "queue",
    "DataBuffer": "buffer", "BufferSync": "buffer", "MergeResult": "buffer",
    "TelemetryRecord": "record", "make_record": "record", "encode_records": "record", "decode_records": "record",
    "telemetry_report": "report", "run_telemetry": "report", "settle_telemetry": "report",
    "fleet_telemetry": "report",
    "StoreError": "errors", "QueueError": "errors", "QueueFullError": "errors", "QueueCorruptError": "errors",
    "QueueWriteError": "errors",
    "TelemetryError": "errors",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
