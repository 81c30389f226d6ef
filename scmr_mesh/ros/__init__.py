"""ROS 2 over rmw_zenoh: the wire contract (:mod:`scmr_mesh.ros.wire`, pure, no Zenoh import).

The bridge that speaks it (``scmr ros``) lives in :mod:`scmr_mesh.mesh.ros` with the other Zenoh code.
See docs/ROS2.md.
"""
