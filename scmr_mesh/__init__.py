"""scmr-mesh: survivable cloud multi-robotics on Eclipse Zenoh.

Robots offload drivable-region segmentation to a cloud tier over Zenoh
queries; a robot leader (a clone of the cloud) serves when the cloud is lost.

Layers, lowest first (dependencies point inward; ``tests/test_layers.py``
enforces it, imports inside functions included):

* base: :mod:`~scmr_mesh.errors`, :mod:`~scmr_mesh.wire`, :mod:`~scmr_mesh.keys`;
* pure cores, no Zenoh and no rerun: :mod:`scmr_mesh.imaging`,
  :mod:`scmr_mesh.energy`, :mod:`scmr_mesh.data`, :mod:`scmr_mesh.qos`,
  :mod:`scmr_mesh.security`, :mod:`scmr_mesh.scenario.spec` and ``.plan``;
* :mod:`scmr_mesh.mesh`: every Zenoh import of the running system;
  :mod:`scmr_mesh.viz`: every rerun import;
* :mod:`scmr_mesh.fleet`, :mod:`scmr_mesh.scenario`: processes and faults;
* ``*/commands.py``: the CLI wiring of each area;
* :mod:`scmr_mesh.bench`: every ``scmr bench`` target (imported only by the CLI);
* :mod:`scmr_mesh.cli`: argument parsing and user-facing output.
"""

from scmr_mesh.errors import ScmrError

__version__ = "0.1.0"
__all__ = ["ScmrError", "__version__"]
