"""Zenoh access-control rules for the scmr mesh (pure: builds the JSON, imports no Zenoh).

Every honest node enforces the same policy on the messages it exchanges with each remote
peer (the *subject*, identified by its certificate CN under mutual TLS, or its user name
under usrpwd).  The default is **deny**; the policy allows:

=================  ======================================================================
subject            allowed (``flows`` as seen by the enforcing node)
=================  ======================================================================
cloud, leader      everything under ``scmr/**`` in both directions (they are the servers)
every robot        ingress ``query`` on ``scmr/drivable/**`` and the data tier's
                   ``scmr/data/*/*/buffer`` (data-buffer reads);
                   egress ``reply`` and ``declare_queryable`` on those keys and on
                   ``scmr/data/*/*/telemetry/*`` (so the robot learns the services and
                   gets answers); egress ``declare_subscriber``
                   on the robot publication keys (so its puts are routed to the servers);
                   liveliness: ingress subscriber/query on ``scmr/alive/**``, egress tokens
                   and replies there; ingress ``declare_subscriber`` and egress ``put`` on
                   the load keys (load spreading)
robot ``<id>``     ingress ``put``/``delete`` on its own ``scmr/telemetry/<id>``,
                   ``scmr/results/<id>``, ``scmr/metrics/<id>``; ingress ``query`` on
                   its own ``scmr/data/*/*/telemetry/<id>`` (telemetry batches); ingress
                   ``liveliness_token`` on its own ``scmr/alive/robot/<id>``
=================  ======================================================================

Everything else from a robot is dropped, in particular: publishing another robot's
telemetry, declaring a queryable on ``scmr/drivable/**`` (a rogue service is never
announced, and queries are never sent to a robot), replying on ``scmr/drivable/**``,
subscribing to other robots' telemetry, storing telemetry batches on another robot's
key ``scmr/data/*/*/telemetry/<other>`` (or on a wildcard), the leader's relay key
``scmr/data/cloud/*/relay``, and reading the data store (the leader's
``scmr/data/cloud/*/sync`` pull, and anything else under ``scmr/data/**``).

Zenoh does not tell a queryable who sent a query; the robot id is in the telemetry key
instead, these rules let robot X query only ``.../telemetry/X``, and the data tier
refuses a batch whose records name another robot than the key
(:func:`scmr_mesh.mesh.data_service.check_sender`).  Together they bind stored
telemetry to the sender's certificate.  Frame requests (``scmr/drivable/**``) are not
bound yet: their ``robot`` field is self-declared (docs/SECURITY.md, "Gaps").

References
----------
Zenoh access control: https://zenoh.io/docs/manual/access-control/ ; the JSON shape
was checked against eclipse-zenoh 1.10.2 (``zenoh.open`` rejects unknown messages).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Sequence

from scmr_mesh import keys
from scmr_mesh.errors import ConfigError
from scmr_mesh.security.credentials import Fleet

#: Every message kind Zenoh 1.10 access control knows.
ALL_MESSAGES: tuple[str, ...] = (
    "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
)
BOTH: list[str] = ["ingress", "egress"]

AuthKind = Literal["tls", "usrpwd"]


@dataclass(frozen=True)
class KeyLayout:
    """Key expressions the policy talks about (defaults from :mod:`scmr_mesh.keys`).

    ``{id}`` in a pattern is replaced by the robot's name.
    """

    root: str = f"{keys.ROOT}/**"
    services: tuple[str, ...] = (keys.DRIVABLE_ALL,)
    robot_query: tuple[str, ...] = (f"{keys.DATA}/*/*/buffer",)
    #: Keys a robot may query only under its own id (``{id}``); replies and the
    #: queryables' declarations go to every robot on the ``*`` form.
    robot_own_query: tuple[str, ...] = (f"{keys.DATA}/*/*/telemetry/{{id}}",)
    robot_publish: tuple[str, ...] = (
        f"{keys.TELEMETRY}/{{id}}", f"{keys.RESULTS}/{{id}}", f"{keys.METRICS}/{{id}}",
    )
    robot_token: str = f"{keys.ALIVE}/robot/{{id}}"
    alive: str = keys.ALIVE_ALL
    load: str = keys.LOAD_ALL

    def publish_all(self) -> list[str]:
        """Every robot publication key, with ``{id}`` as a wildcard chunk."""
        return [p.replace("{id}", "*") for p in self.robot_publish]

    def own_query_all(self) -> list[str]:
        """Every robot's own query keys, with ``{id}`` as a wildcard chunk."""
        return [p.replace("{id}", "*") for p in self.robot_own_query]


def _rule(rid: str, messages: Sequence[str], flows: Sequence[str], key_exprs: Sequence[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "permission": "allow",
        "flows": list(flows),
        "messages": list(messages),
        "key_exprs": list(key_exprs),
    }


def _subject(sid: str, kind: AuthKind, names: Sequence[str]) -> dict[str, Any]:
    attr = "cert_common_names" if kind == "tls" else "usernames"
    return {"id": sid, attr: list(names)}


def build_acl(fleet: Fleet, *, kind: AuthKind, layout: KeyLayout = KeyLayout()) -> dict[str, Any]:
    """The ``access_control`` object for every node of ``fleet``.

    Parameters
    ----------
    fleet : Fleet
        Identities and roles (``fleet.json`` of a credentials directory).
    kind : {"tls", "usrpwd"}, keyword-only
        How peers are identified: certificate common names or usrpwd user names.
    layout : KeyLayout, keyword-only
        Key expressions to use (defaults follow :mod:`scmr_mesh.keys`).

    Returns
    -------
    dict
        ``{"enabled": True, "default_permission": "deny", "rules": [...],
        "subjects": [...], "policies": [...]}``, ready for
        ``config.insert_json5("access_control", json.dumps(acl))``.

    Raises
    ------
    ConfigError
        ``kind`` is unknown or the fleet has no peers.

    Examples
    --------
    >>> from scmr_mesh.security.credentials import Fleet, Peer
    >>> acl = build_acl(Fleet((Peer("cloud", "cloud"), Peer("r1", "robot"))), kind="tls")
    >>> acl["default_permission"]
    'deny'
    """
    if kind not in ("tls", "usrpwd"):
        raise ConfigError(f"security kind {kind!r} has no identities for ACL; use 'tls' or 'usrpwd'")
    if not fleet.peers:
        raise ConfigError("the fleet has no peers; create credentials with `scmr certs --peers ...`")
    served = list(layout.services) + list(layout.robot_query)
    rules = [
        _rule("servers-all", ALL_MESSAGES, BOTH, [layout.root]),
        _rule("robots-query-services", ["query"], ["ingress"], served),
        _rule("robots-get-replies", ["reply", "declare_queryable"], ["egress"],
              served + layout.own_query_all()),
        _rule("robots-reach-subscribers", ["declare_subscriber"], ["egress"], layout.publish_all()),
        _rule(
            "robots-watch-liveliness",
            ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"], [layout.alive],
        ),
        _rule("robots-see-liveliness", ["liveliness_token", "reply"], ["egress"], [layout.alive]),
        _rule("robots-read-load", ["declare_subscriber"], ["ingress"], [layout.load]),
        _rule("robots-get-load", ["put"], ["egress"], [layout.load]),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if fleet.servers:
        subjects.append(_subject("servers", kind, fleet.servers))
        policies.append({"id": "servers", "rules": ["servers-all"], "subjects": ["servers"]})
    if fleet.robots:
        subjects.append(_subject("robots", kind, fleet.robots))
        policies.append(
            {
                "id": "robots",
                "rules": [r["id"] for r in rules[1:]],
                "subjects": ["robots"],
            }
        )
    for name in fleet.robots:
        own = [p.replace("{id}", name) for p in layout.robot_publish]
        rules.append(_rule(f"robot-{name}-own-data", ["put", "delete"], ["ingress"], own))
        rules.append(_rule(f"robot-{name}-own-queries", ["query"], ["ingress"],
                           [p.replace("{id}", name) for p in layout.robot_own_query]))
        rules.append(
            _rule(f"robot-{name}-own-token", ["liveliness_token"], ["ingress"],
                  [layout.robot_token.replace("{id}", name)])
        )
        subjects.append(_subject(f"robot-{name}", kind, [name]))
        policies.append(
            {
                "id": f"robot-{name}",
                "rules": [f"robot-{name}-own-data", f"robot-{name}-own-queries", f"robot-{name}-own-token"],
                "subjects": [f"robot-{name}"],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
