"""scmr-mesh: survivable cloud multi-robotics on Eclipse Zenoh.

Robots offload drivable-region segmentation to a cloud tier over Zenoh
queries; a robot leader (a clone of the cloud) serves when the cloud is lost.

Layers (dependencies point inward; ``tests/test_layers.py`` enforces it):

* pure core: :mod:`scmr_mesh.imaging`, :mod:`scmr_mesh.energy`,
  :mod:`scmr_mesh.wire`, :mod:`scmr_mesh.scenario.spec` - no Zenoh, no rerun;
* :mod:`scmr_mesh.mesh` - every Zenoh import lives here;
* :mod:`scmr_mesh.viz` - the only module that imports rerun;
* :mod:`scmr_mesh.cli` - argument parsing and user-facing output.
"""

from scmr_mesh.errors import ScmrError

__version__ = "0.1.0"
__all__ = ["ScmrError", "__version__"]
