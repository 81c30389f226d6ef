"""Names shared by the viz modules: ids, ports, classes, entity roots, the viz error."""

from __future__ import annotations

import re

from scmr_mesh import keys
from scmr_mesh.errors import ScmrError

#: Application id shared by every process of a fleet run.
APP_ID = "scmr-mesh"
#: Default viewer port (the one rerun's own examples use).
DEFAULT_PORT = 9876
#: Default web-viewer port of ``--serve``.
DEFAULT_WEB_PORT = 9090
#: ``--connect`` without a URL connects here.
DEFAULT_CONNECT_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"
#: Class ids of the drivability map, with label and RGBA colour.
CLASSES: tuple[tuple[int, str, tuple[int, int, int, int]], ...] = (
    (1, "drivable", (0, 200, 0, 255)),
    (2, "non-drivable", (220, 0, 0, 255)),
)
#: Serving tier drawn as a level in the tier plot (``failed`` = no answer).
TIER_LEVEL: dict[str | None, int] = {"cloud": 3, "leader": 2, "peer": 1, "local": 0, None: -1, "failed": -1}
#: Annotation-context root: everything under it shares the class colours.
ROBOT_ROOT = f"{keys.ROOT}/robot"
FAULTS = f"{keys.ROOT}/faults"
FLEET = f"{keys.ROOT}/fleet"

#: Environment fallback for peers started by a runner that cannot pass flags
#: (``scmr scenario run``): the sink URL, or a folder for one ``<peer>.rrd``
#: each (peers in network namespaces cannot reach the host's loopback), and
#: the shared recording id.
ENV_URL, ENV_SAVE_DIR, ENV_RECORDING_ID = "SCMR_RERUN_URL", "SCMR_RERUN_SAVE_DIR", "SCMR_RERUN_RECORDING_ID"

_URL_RE = re.compile(r"^(rerun|rerun\+http|rerun\+https)://[^/\s]+/proxy$")


class ViewerError(ScmrError):
    """The rerun viewer or sink could not be started, reached or read."""



def entity_name(text: str) -> str:
    """``text`` as one entity-path/key chunk: runs of other characters become ``_``.

    >>> entity_name("cloud | leader,robot1")
    'cloud_leader_robot1'
    """
    name = re.sub(r"[^A-Za-z0-9_.\-]+", "_", text).strip("_")[:64]
    return name or "_"


