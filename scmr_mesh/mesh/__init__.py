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

from scmr_mesh._lazy import lazy_exports

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


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
