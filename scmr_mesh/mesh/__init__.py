"""The mesh: Zenoh peers serving and requesting drivable-region segmentation.

The only package that imports ``zenoh`` (tests/test_layers.py).  Modules:

``config``    zenoh configuration in layers, validated (lease/keep-alive traps)
``server``    :class:`Service`: the cloud/leader queryable, worker pool, hooks
``work``      :class:`WorkerPool` and the per-request process function
``robot``     :class:`Robot`: live view, routing, failover, records, hooks
``peers``     :func:`run_service`, :func:`run_router`: signals, ready files
``commands``  ``scmr cloud | leader | robot | router`` and ``scmr bench zenoh``
``testing``   stub process functions and process helpers for tests
``probe``     measurements behind docs/ZENOH.md
``netns``     two network namespaces joined by a veth pair (cross-host tests)

Keys are in :mod:`scmr_mesh.keys`, messages in :mod:`scmr_mesh.wire`; the
catalog is docs/protocol.md.  Public names are imported lazily::

    from scmr_mesh.mesh import Robot, Service, MeshConfig, run_service
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "MeshConfig": "config",
    "build_config": "config",
    "open_session": "config",
    "close_session": "config",
    "Service": "server",
    "Refusal": "server",
    "ServiceState": "server",
    "default_admission": "server",
    "WorkerPool": "work",
    "Robot": "robot",
    "RobotOptions": "robot",
    "LiveView": "robot",
    "Reachable": "robot",
    "FrameInfo": "robot",
    "default_placement": "robot",
    "run_service": "peers",
    "run_router": "peers",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
