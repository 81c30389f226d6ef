"""Key expressions of the scmr mesh: one catalog, used by every peer.

Pure module (no Zenoh import): the strings here are Zenoh key expressions and
double as rerun entity paths, so the viewer's tree mirrors the mesh.  The
catalog with message formats is in ``docs/protocol.md``.

==========================================  ===========================  ============================
key expression                              declared by                  carries
==========================================  ===========================  ============================
``scmr/drivable/cloud/<node>/<robot>``      cloud service (queryable     request of <robot> -> reply | error
                                            on ``.../<node>/*``)
``scmr/drivable/leader/<node>/<robot>``     the current leader           request -> reply | error
``scmr/drivable/peer/<node>/<robot>``       a robot serving peers        request -> reply | error
``scmr/alive/cloud/<node>``                 cloud (liveliness token)     presence of a cloud node
``scmr/alive/leader/<node>``                the leader (liveliness)      who leads (held while leading)
``scmr/alive/candidate/<node>``             leader-capable node          presence of a candidate
``scmr/alive/peer/<robot>``                 robot serving peers          presence of a peer server
``scmr/alive/robot/<robot>``                robot (liveliness token)     presence of a robot
``scmr/load/cloud/<node>``                  cloud (publisher)            load message (spreading)
``scmr/load/leader/<node>``                 leader (publisher)           load message
``scmr/load/peer/<robot>``                  robot serving peers          load message (with capability)
``scmr/r2r/candidate/<node>``               candidate (pub + queryable)  candidacy: term, rank inputs
``scmr/telemetry/<robot>``                  robot (publisher)            telemetry message
``scmr/results/<robot>``                    robot (publisher)            one record per request
``scmr/metrics/<node>``                     any peer (publisher)         free-form metrics
``scmr/data/<tier>/<node>/**``              services (extra queryables)  data-buffer queries
==========================================  ===========================  ============================

A frame request goes to ``scmr/drivable/<tier>/<node>/<robot>``: the sender's
id is the last chunk, so access control lets robot X query only keys ending
in ``/X``, and the service refuses a request whose ``robot`` field differs
(:func:`drivable_request`, :func:`request_robot`).  Services reply on the
concrete key the request came on.

Under ``scmr/data/<tier>/<node>/``: ``telemetry/<robot>`` carries one robot's
telemetry batches (the robot id is in the key so that access control can bind
it to the sender's identity; :func:`data_telemetry`), ``relay`` the leader's
forwarded batches to the cloud (:func:`data_relay`), ``buffer`` and ``sync``
data-buffer reads.

The R2R tier (docs/R2R.md): leadership is a role.  Every leader-capable node
holds ``scmr/alive/candidate/<node>`` and publishes its candidacy; the
elected one declares the leader queryable and token under its own name, so
the leader's key changes when the lead passes on.  Candidates that do not
lead serve other robots on ``scmr/drivable/peer/<robot>``.

Tiers are distinct key spaces on purpose: a query on one shared key would go
to both cloud and leader (zenoh facts sheet, section 2).  Node and robot names
must be single key chunks (no ``/``, ``*``, ``$``, ``?``, ``#``); use
:func:`check_name`.
"""

from __future__ import annotations

import re

from scmr_mesh.errors import InputError

#: Root of every scmr key.
ROOT = "scmr"
#: Serving tiers, in the default order of preference.
TIERS: tuple[str, ...] = ("cloud", "leader", "peer")
#: Where a request can end up: a serving tier or the robot itself.
PLACEMENTS: tuple[str, ...] = ("cloud", "leader", "peer", "local")
#: Roles that hold a liveliness token.
ROLES: tuple[str, ...] = ("cloud", "leader", "peer", "candidate", "robot")

DRIVABLE = f"{ROOT}/drivable"
ALIVE = f"{ROOT}/alive"
LOAD = f"{ROOT}/load"
TELEMETRY = f"{ROOT}/telemetry"
RESULTS = f"{ROOT}/results"
METRICS = f"{ROOT}/metrics"
DATA = f"{ROOT}/data"
R2R = f"{ROOT}/r2r"

#: Every drivable queryable.
DRIVABLE_ALL = f"{DRIVABLE}/**"
#: Every liveliness token (subscribe with ``history=True``).
ALIVE_ALL = f"{ALIVE}/**"
#: Every load publication.
LOAD_ALL = f"{LOAD}/**"
#: Every telemetry publication.
TELEMETRY_ALL = f"{TELEMETRY}/*"
#: Every results publication.
RESULTS_ALL = f"{RESULTS}/*"
#: Every candidacy publication / queryable of the R2R election.
CANDIDATES_ALL = f"{R2R}/candidate/*"

_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_name(name: str, *, what: str = "node name") -> str:
    """Return ``name`` if it is usable as one key chunk, else raise.

    Parameters
    ----------
    name : str
        A node or robot name: 1-64 characters from ``A-Z a-z 0-9 _ . -``.
    what : str
        What the name is, for the error message.

    Raises
    ------
    InputError
        When the name is empty, too long, or has characters that are special
        in key expressions.
    """
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise InputError(
            f"{what} must be 1-64 characters from A-Z a-z 0-9 _ . - (got {name!r}); "
            "pick a plain name such as 'cloud1' or 'robot-3'"
        )
    return name


def _tier(tier: str) -> str:
    if tier not in TIERS:
        raise InputError(f"tier must be one of {TIERS}, got {tier!r}")
    return tier


def drivable(tier: str, node: str) -> str:
    """Prefix of the drivable-region service of ``node`` serving ``tier``.

    >>> drivable("cloud", "c1")
    'scmr/drivable/cloud/c1'
    """
    return f"{DRIVABLE}/{_tier(tier)}/{check_name(node)}"


def drivable_serve(tier: str, node: str) -> str:
    """Key expression of ``node``'s drivable queryable: one key per requesting robot.

    >>> drivable_serve("cloud", "c1")
    'scmr/drivable/cloud/c1/*'
    """
    return f"{drivable(tier, node)}/*"


def drivable_request(tier: str, node: str, robot: str) -> str:
    """Key on which ``robot`` sends its frame requests to ``node`` of ``tier``.

    >>> drivable_request("leader", "L", "r1")
    'scmr/drivable/leader/L/r1'
    """
    return f"{drivable(tier, node)}/{check_name(robot, what='robot id')}"


def request_target(key: str) -> tuple[str, str, str] | None:
    """``(tier, node, robot)`` of a concrete request key ``scmr/drivable/<tier>/<node>/<robot>``.

    None unless ``key`` has exactly that shape with plain chunks: a wildcard
    (``*``, ``**``, ``$*``) names no node or robot.

    >>> request_target("scmr/drivable/cloud/c1/r1")
    ('cloud', 'c1', 'r1')
    >>> request_target("scmr/drivable/**") is None
    True
    """
    parts = str(key).split("/")
    if (len(parts) != 5 or f"{parts[0]}/{parts[1]}" != DRIVABLE or parts[2] not in TIERS
            or not _NAME_RE.match(parts[3]) or not _NAME_RE.match(parts[4])):
        return None
    return parts[2], parts[3], parts[4]


def drivable_tier(tier: str) -> str:
    """Key expression matching every node of one tier (``scmr/drivable/<tier>/*``)."""
    return f"{DRIVABLE}/{_tier(tier)}/*"


def candidate_node(key: str) -> str | None:
    """The node named by a candidacy key ``scmr/r2r/candidate/<node>`` (None if not concrete).

    >>> candidate_node("scmr/r2r/candidate/r2")
    'r2'
    """
    parts = str(key).split("/")
    if len(parts) != 4 or f"{parts[0]}/{parts[1]}" != R2R or parts[2] != "candidate" or not _NAME_RE.match(parts[3]):
        return None
    return parts[3]


def candidate(node: str) -> str:
    """Key on which leader-capable ``node`` publishes (and answers) its candidacy.

    >>> candidate("r2")
    'scmr/r2r/candidate/r2'
    """
    return f"{R2R}/candidate/{check_name(node)}"


def alive(role: str, node: str) -> str:
    """Liveliness token key of ``node`` in ``role`` (cloud, leader or robot).

    >>> alive("leader", "L")
    'scmr/alive/leader/L'
    """
    if role not in ROLES:
        raise InputError(f"role must be one of {ROLES}, got {role!r}")
    return f"{ALIVE}/{role}/{check_name(node)}"


def load(tier: str, node: str) -> str:
    """Key on which a service publishes its load (``scmr/load/<tier>/<node>``)."""
    return f"{LOAD}/{_tier(tier)}/{check_name(node)}"


def telemetry(robot: str) -> str:
    """Key on which ``robot`` publishes telemetry (``scmr/telemetry/<robot>``)."""
    return f"{TELEMETRY}/{check_name(robot, what='robot id')}"


def results(robot: str) -> str:
    """Key on which ``robot`` publishes one record per finished request."""
    return f"{RESULTS}/{check_name(robot, what='robot id')}"


def metrics(node: str) -> str:
    """Key on which a peer may publish metrics (``scmr/metrics/<node>``)."""
    return f"{METRICS}/{check_name(node)}"


def data(tier: str, node: str, name: str = "**") -> str:
    """Key prefix for extra (data-buffer) queryables of a service."""
    return f"{DATA}/{_tier(tier)}/{check_name(node)}/{name}"


def data_telemetry(tier: str, node: str, robot: str | None = None) -> str:
    """Key of ``robot``'s telemetry batches to ``node`` of ``tier``.

    The robot id is in the key so that access control can allow each robot
    only its own key (docs/SECURITY.md); the service refuses a batch whose
    records name another robot.  ``robot=None`` gives the queryable's key
    expression (``.../telemetry/*``).

    >>> data_telemetry("cloud", "c1", "r1")
    'scmr/data/cloud/c1/telemetry/r1'
    >>> data_telemetry("leader", "L")
    'scmr/data/leader/L/telemetry/*'
    """
    who = "*" if robot is None else check_name(robot, what="robot id")
    return data(tier, node, f"telemetry/{who}")


def data_relay(node: str) -> str:
    """Key on which a leader forwards relayed telemetry (any robots) to cloud ``node``.

    Only server identities may query it (access control).

    >>> data_relay("c1")
    'scmr/data/cloud/c1/relay'
    """
    return data("cloud", node, "relay")


def telemetry_robot(key: str) -> str | None:
    """The robot named by a telemetry key ``scmr/data/<tier>/<node>/telemetry/<robot>``.

    Returns None unless ``key`` has exactly that shape with a plain robot
    chunk: a wildcard (``*``, ``**``, ``$*``) names no robot.

    >>> telemetry_robot("scmr/data/cloud/c1/telemetry/r1")
    'r1'
    >>> telemetry_robot("scmr/data/cloud/c1/telemetry/*") is None
    True
    """
    parts = str(key).split("/")
    if (len(parts) != 6 or parts[0] != ROOT or f"{parts[0]}/{parts[1]}" != DATA
            or parts[2] not in TIERS or parts[4] != "telemetry" or not _NAME_RE.match(parts[5])):
        return None
    return parts[5]


def parse(key: str) -> tuple[str, str, str]:
    """Split ``scmr/<kind>/<role>/<node>`` into ``(kind, role, node)``.

    Parameters
    ----------
    key : str
        A key such as ``scmr/alive/cloud/c1``.

    Returns
    -------
    tuple of str
        ``("alive", "cloud", "c1")``.

    Raises
    ------
    InputError
        When the key does not have four chunks under ``scmr/``.
    """
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != ROOT:
        raise InputError(f"expected a key scmr/<kind>/<role>/<node>, got {key!r}")
    return parts[1], parts[2], parts[3]
