"""Zenoh access-control rules for the scmr mesh (pure: builds the JSON, imports no Zenoh).

Every honest node enforces the same policy on the messages it exchanges with each remote
peer (the *subject*, identified by its certificate CN under mutual TLS).  The default is
**deny**.  ``ingress`` rules say what a subject may send us, ``egress`` rules what we may
send to it; both ends of every link check, so a message passes only when the sender's
egress and the receiver's ingress allow it.

==========================  =================================================================
subject                     allowed
==========================  =================================================================
cloud, router               everything under ``scmr/**``, both directions (trusted infrastructure)
every other identity        ingress: liveliness subscriptions and queries on ``scmr/alive/**``;
(robots, leaders)           subscribing to loads and candidacies; reading the data buffers
                            (``scmr/data/*/*/buffer``).  egress: queryable, subscriber and
                            liveliness declarations, tokens, loads and candidacies (so it sees
                            the services and the election)
robot ``X``                 ingress: frame requests on its **own** key ``scmr/drivable/*/*/X``,
                            telemetry batches on its own ``scmr/data/*/*/telemetry/X``, put/delete
                            on its own ``scmr/{telemetry,results,metrics}/X``, its own token
                            ``scmr/alive/robot/X``; egress: replies on those keys only
leader-capable ``L``        ingress, all under its own name only: the leader and peer queryables
(``scmr leader``, robots    ``scmr/drivable/{leader,peer}/L/*`` and their replies, the leader's data
with ``+leader-capable``)   queryables ``scmr/data/leader/L/**``, tokens ``scmr/alive/{leader,peer,
                            candidate}/L``, loads ``scmr/load/{leader,peer}/L``, candidacy
                            ``scmr/r2r/candidate/L`` (publication, queryable, replies); queries
                            of every candidacy, the leader's and the clouds' ``sync`` and the
                            clouds' ``relay``.  egress: frame requests, telemetry batches and
                            buffer reads to its leader/peer/data keys, candidacy queries
==========================  =================================================================

So a robot certificate cannot serve as a cloud (no ``scmr/drivable/cloud/...`` queryable,
reply or ``scmr/alive/cloud/...`` token from it is accepted), a plain robot cannot serve
other robots or run for the lead, and a candidate can claim the lead only under its own
name (robot X may publish only ``scmr/r2r/candidate/X``; the election also checks that a
candidacy names the key it came on).  Frame requests and telemetry are bound to the
sender: robot X may query only keys ending in ``/X``, and the services refuse a request
whose ``robot`` field differs from the key (:mod:`scmr_mesh.mesh.server`).  A wildcard
query is not let through by a rule that merely intersects it (docs/SECURITY.md, fact 8).

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

    ``{id}`` in a pattern is replaced by the identity's name.
    """

    root: str = f"{keys.ROOT}/**"
    alive: str = keys.ALIVE_ALL
    load: str = keys.LOAD_ALL
    candidates: str = keys.CANDIDATES_ALL
    #: queries every identity may send (shared data: the data buffers)
    shared_query: tuple[str, ...] = (f"{keys.DATA}/*/*/buffer",)
    #: queries an identity may send only under its own name
    own_query: tuple[str, ...] = (f"{keys.DRIVABLE}/*/*/{{id}}", f"{keys.DATA}/*/*/telemetry/{{id}}")
    own_publish: tuple[str, ...] = (
        f"{keys.TELEMETRY}/{{id}}", f"{keys.RESULTS}/{{id}}", f"{keys.METRICS}/{{id}}",
    )
    own_token: str = f"{keys.ALIVE}/robot/{{id}}"
    #: what a leader-capable identity serves, under its own name
    lead_serve: tuple[str, ...] = (
        f"{keys.DRIVABLE}/leader/{{id}}/*", f"{keys.DRIVABLE}/peer/{{id}}/*", f"{keys.DATA}/leader/{{id}}/**",
        f"{keys.R2R}/candidate/{{id}}",
    )
    lead_tokens: tuple[str, ...] = (
        f"{keys.ALIVE}/leader/{{id}}", f"{keys.ALIVE}/peer/{{id}}", f"{keys.ALIVE}/candidate/{{id}}",
    )
    lead_publish: tuple[str, ...] = (
        f"{keys.LOAD}/leader/{{id}}", f"{keys.LOAD}/peer/{{id}}", f"{keys.R2R}/candidate/{{id}}",
    )
    #: what a leader-capable identity queries besides its own keys (election, leader data)
    lead_query: tuple[str, ...] = (
        keys.CANDIDATES_ALL, f"{keys.DATA}/leader/*/sync", f"{keys.DATA}/cloud/*/sync", f"{keys.DATA}/cloud/*/relay",
    )

    @staticmethod
    def own(patterns, name: str) -> list[str]:
        """``patterns`` with ``{id}`` replaced by ``name``."""
        if isinstance(patterns, str):
            patterns = (patterns,)
        return [p.replace("{id}", name) for p in patterns]

    @staticmethod
    def any(patterns) -> list[str]:
        """``patterns`` with ``{id}`` as a wildcard chunk."""
        if isinstance(patterns, str):
            patterns = (patterns,)
        return [p.replace("{id}", "*") for p in patterns]


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


def member_rules(layout: KeyLayout = KeyLayout()) -> list[dict[str, Any]]:
    """Rules for every identity that is not trusted infrastructure (robots and leaders)."""
    k = layout
    return [
        _rule("members-watch", ["declare_liveliness_subscriber", "liveliness_query"], BOTH, [k.alive]),
        _rule("members-subscribe", ["declare_subscriber"], ["ingress"], [k.load, k.candidates]),
        _rule("members-read-buffers", ["query"], ["ingress"], list(k.shared_query)),
        _rule("members-see-services", ["declare_queryable"], ["egress"],
              [f"{keys.DRIVABLE}/**", f"{keys.DATA}/**", k.candidates]),
        _rule("members-reach-subscribers", ["declare_subscriber"], ["egress"],
              [*k.any(k.own_publish), k.load, k.candidates]),
        _rule("members-see-liveliness", ["liveliness_token"], ["egress"], [k.alive]),
        _rule("members-get-loads", ["put"], ["egress"], [k.load, k.candidates]),
        _rule("members-get-shared-replies", ["reply"], ["egress"], [k.alive, *k.shared_query, k.candidates]),
    ]


def own_rules(name: str, layout: KeyLayout = KeyLayout()) -> list[dict[str, Any]]:
    """Rules of identity ``name``: what it may do under its own name."""
    k = layout
    return [
        _rule(f"{name}-own-queries", ["query"], ["ingress"], k.own(k.own_query, name)),
        _rule(f"{name}-own-replies", ["reply"], ["egress"], k.own(k.own_query, name)),
        _rule(f"{name}-own-data", ["put", "delete"], ["ingress"], k.own(k.own_publish, name)),
        _rule(f"{name}-own-token", ["liveliness_token"], ["ingress"], k.own(k.own_token, name)),
        _rule(f"{name}-own-token-replies", ["reply"], ["ingress"], k.own(k.own_token, name)),
    ]


def lead_rules(name: str, layout: KeyLayout = KeyLayout()) -> list[dict[str, Any]]:
    """Rules of a leader-capable identity ``name``: serve the leader/peer tiers and run for the lead."""
    k = layout
    serve = k.own(k.lead_serve, name)
    return [
        _rule(f"{name}-lead-serve", ["declare_queryable"], ["ingress"], serve),
        _rule(f"{name}-lead-replies", ["reply"], ["ingress"], [*serve, *k.own(k.lead_tokens, name)]),
        _rule(f"{name}-lead-tokens", ["liveliness_token"], ["ingress"], k.own(k.lead_tokens, name)),
        _rule(f"{name}-lead-publish", ["put"], ["ingress"], k.own(k.lead_publish, name)),
        _rule(f"{name}-lead-queries", ["query"], ["ingress"], list(k.lead_query)),
        _rule(f"{name}-lead-reached", ["query"], ["egress"], [*serve, k.candidates]),
        _rule(f"{name}-lead-answered", ["reply"], ["egress"], list(k.lead_query)),
    ]


def build_acl(fleet: Fleet, *, kind: AuthKind, layout: KeyLayout = KeyLayout()) -> dict[str, Any]:
    """The ``access_control`` object for every node of ``fleet``.

    Parameters
    ----------
    fleet : Fleet
        Identities, roles and lead grants (``fleet.json`` of a credentials directory).
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
    rules = [_rule("trusted-all", ALL_MESSAGES, BOTH, [layout.root])]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if fleet.trusted:
        subjects.append(_subject("trusted", kind, fleet.trusted))
        policies.append({"id": "trusted", "rules": ["trusted-all"], "subjects": ["trusted"]})
    if fleet.members:
        shared = member_rules(layout)
        rules += shared
        subjects.append(_subject("members", kind, fleet.members))
        policies.append({"id": "members", "rules": [r["id"] for r in shared], "subjects": ["members"]})
    for peer in fleet.peers:
        if peer.trusted:
            continue
        mine = own_rules(peer.name, layout) + (lead_rules(peer.name, layout) if peer.leads else [])
        rules += mine
        subjects.append(_subject(f"id-{peer.name}", kind, [peer.name]))
        policies.append({"id": f"id-{peer.name}", "rules": [r["id"] for r in mine], "subjects": [f"id-{peer.name}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
