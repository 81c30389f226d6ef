"""Development credentials for an authenticated mesh: a CA, per-peer certificates, passwords.

``scmr certs --out DIR --peers cloud,leader,robot1`` calls :func:`create_credentials`,
which writes::

    DIR/ca.pem, DIR/ca.key            development certificate authority (keep ca.key offline)
    DIR/<peer>/cert.pem, key.pem      the peer's certificate (CN = peer name) and private key
    DIR/<peer>/password               the peer's usrpwd password (the lighter option)
    DIR/<peer>/usrpwd.txt             the usrpwd dictionary this peer checks incoming links against
    DIR/fleet.json                    peer names and roles (cloud, leader, robot): the ACL's input

Certificates are made with the ``cryptography`` package (EC P-256, SHA-256).
Private keys and passwords are written with mode 0600.

This module is pure: it imports neither Zenoh nor rerun.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from scmr_mesh.errors import ConfigError, InputError

log = logging.getLogger(__name__)

#: Roles a peer may have.  ``cloud`` nodes and ``router`` s are trusted infrastructure
#: (they may serve and forward everything under ``scmr/**``); a ``leader`` is a dedicated
#: candidate for the lead of the R2R tier; a ``robot`` is a client, which may also run for
#: the lead when its identity is *leader-capable* (``name=robot+leader-capable``).
ROLES: tuple[str, ...] = ("cloud", "leader", "robot", "router")
#: Roles trusted with everything (they are the fleet's infrastructure).
TRUSTED_ROLES: frozenset[str] = frozenset({"cloud", "router"})
#: Roles that serve frames: cloud nodes, and leader-capable identities on the leader and peer tiers.
SERVER_ROLES: frozenset[str] = frozenset({"cloud", "leader"})
#: The attribute of a robot identity allowed to run for the lead and serve other robots.
LEADER_CAPABLE = "leader-capable"

#: Peer names double as certificate common names, usrpwd user names and key-expression
#: chunks, so they are restricted to a safe alphabet.
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,62}$")

FLEET_FILE = "fleet.json"
#: Version 2 adds ``leader_capable`` and ``priority_cap``; version 1 files still load.
FLEET_VERSION = 2
#: Highest priority a request may carry (``schemas/request.schema.json``).
MAX_PRIORITY = 1_000_000


@dataclass(frozen=True)
class Peer:
    """One identity of the mesh.

    Parameters
    ----------
    name : str
        Peer name: certificate CN, usrpwd user name and node id (``robot1``).
    role : str
        One of :data:`ROLES`.
    leader_capable : bool
        May run for the lead of the R2R tier and serve other robots (always true for
        ``leader``; a robot needs ``+leader-capable``).
    priority_cap : int or None
        Highest priority a service grants this identity's frame requests (the fleet's
        policy: a request asking more is served at the cap).  ``None``: no cap.
    """

    name: str
    role: str
    leader_capable: bool = False
    priority_cap: int | None = None

    @property
    def is_server(self) -> bool:
        """True for identities that serve frames: cloud nodes and lead candidates."""
        return self.role in SERVER_ROLES or self.leads

    @property
    def trusted(self) -> bool:
        """Cloud nodes and routers: trusted with everything under ``scmr/**``."""
        return self.role in TRUSTED_ROLES

    @property
    def leads(self) -> bool:
        """May hold the lead and serve the leader and peer tiers (dedicated leader, leader-capable robot)."""
        return self.role == "leader" or self.leader_capable

    def may_serve(self, tier: str) -> bool:
        """Whether this identity may answer frame requests on ``tier`` (cloud, leader, peer)."""
        if tier == "cloud":
            return self.role == "cloud"
        if tier in ("leader", "peer"):
            return self.leads
        return False

    def spec(self) -> str:
        """The ``--peers`` item that makes this peer again (``r1=robot+leader-capable``)."""
        return f"{self.name}={self.role}" + (f"+{LEADER_CAPABLE}" if self.leader_capable and self.role != "leader"
                                             else "")

    def to_json(self) -> dict:
        out: dict = {"name": self.name, "role": self.role, "leader_capable": self.leads}
        if self.priority_cap is not None:
            out["priority_cap"] = self.priority_cap
        return out


@dataclass(frozen=True)
class Fleet:
    """The identities a credentials directory was made for (``fleet.json``)."""

    peers: tuple[Peer, ...]
    directory: Path | None = field(default=None, compare=False)

    def names(self, *, role: str | None = None) -> list[str]:
        """Peer names, optionally only those of one role."""
        return [p.name for p in self.peers if role is None or p.role == role]

    @property
    def servers(self) -> list[str]:
        """Names of the identities that serve frames (cloud, leader, leader-capable robots)."""
        return [p.name for p in self.peers if p.is_server]

    @property
    def trusted(self) -> list[str]:
        """Names of the cloud and router identities."""
        return [p.name for p in self.peers if p.trusted]

    @property
    def robots(self) -> list[str]:
        """Names of the robot identities."""
        return [p.name for p in self.peers if p.role == "robot"]

    @property
    def members(self) -> list[str]:
        """Names of every identity that is not trusted infrastructure (robots and leaders)."""
        return [p.name for p in self.peers if not p.trusted]

    @property
    def leaders(self) -> list[str]:
        """Names of the identities that may hold the lead (dedicated leaders, leader-capable robots)."""
        return [p.name for p in self.peers if p.leads]

    def find(self, name: str) -> Peer | None:
        for p in self.peers:
            if p.name == name:
                return p
        return None

    def get(self, name: str) -> Peer:
        """The peer called ``name``; :class:`ConfigError` if there is none."""
        p = self.find(name)
        if p is not None:
            return p
        where = f" in {self.directory / FLEET_FILE}" if self.directory else ""
        raise ConfigError(
            f"no credentials for peer {name!r}{where} (known: {', '.join(self.names())}); "
            f"re-run `scmr certs --peers ...` including {name!r}"
        )

    def may_serve(self, tier: str, node: str) -> bool:
        """Whether identity ``node`` may answer frame requests on ``tier`` (unknown names: no)."""
        p = self.find(node)
        return p is not None and p.may_serve(tier)

    def priority_cap(self, robot: str) -> int | None:
        """The highest priority granted to ``robot``'s requests (0 for an unknown name; None: no cap)."""
        p = self.find(robot)
        if p is None:
            return 0
        return p.priority_cap


def infer_role(name: str) -> str:
    """Role from a peer name: ``cloud*`` -> cloud, ``leader*`` -> leader, ``router*`` -> router, else robot."""
    low = name.lower()
    if low.startswith("cloud"):
        return "cloud"
    if low.startswith("leader"):
        return "leader"
    if low.startswith("router"):
        return "router"
    return "robot"


def parse_peers(spec: str | Sequence[str], *, priority: Mapping[str, int] | None = None,
                default_priority_cap: int | None = 0) -> list[Peer]:
    """Parse ``"cloud,leader,r1=robot+leader-capable,edge=cloud"`` into peers.

    A bare name gets its role from :func:`infer_role`; ``name=role`` sets it explicitly;
    ``+leader-capable`` after a robot's role lets it run for the lead and serve other robots.

    Parameters
    ----------
    priority : mapping, optional, keyword-only
        ``{robot: cap}``: the highest priority each robot's frame requests are served at.
    default_priority_cap : int or None, keyword-only
        The cap of robots not in ``priority`` (default 0: every robot equal unless granted).

    Raises
    ------
    InputError
        On an empty list, a bad name, an unknown role or attribute, or a duplicate.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    items = [i.strip() for i in items if i.strip()]
    if not items:
        raise InputError("--peers is empty; give names such as --peers cloud,leader,robot1,robot2")
    priority = dict(priority or {})
    peers: list[Peer] = []
    seen: set[str] = set()
    for item in items:
        name, _, rolespec = item.partition("=")
        name = name.strip()
        role, *attrs = [a.strip() for a in rolespec.split("+")] if rolespec.strip() else [infer_role(name)]
        role = role or infer_role(name)
        if not NAME_RE.match(name):
            raise InputError(
                f"peer name {name!r} is not allowed: use 1-63 letters, digits, '-' or '_', "
                "starting with a letter or digit (for example robot1)"
            )
        if role not in ROLES:
            raise InputError(f"peer {name!r} has role {role!r}; use one of {', '.join(ROLES)}")
        bad = [a for a in attrs if a != LEADER_CAPABLE]
        if bad or (attrs and role not in ("robot", "leader")):
            raise InputError(f"peer {name!r}: attribute {'+'.join(bad or attrs)!r} is not allowed for role {role!r}; "
                             f"only a robot takes +{LEADER_CAPABLE} (e.g. r1=robot+{LEADER_CAPABLE})")
        if name in seen:
            raise InputError(f"peer {name!r} is listed twice in --peers; list each peer once")
        seen.add(name)
        cap = None if role in TRUSTED_ROLES else priority.pop(name, default_priority_cap)
        peers.append(Peer(name, role, leader_capable=role == "leader" or bool(attrs), priority_cap=cap))
    if priority:
        raise InputError(f"--priority-cap names {', '.join(sorted(priority))}, not in --peers; "
                         "give caps for listed robots only")
    if not any(p.is_server for p in peers):
        log.warning("no cloud or leader identity in %s: nobody will be allowed to serve", items)
    return peers


def parse_priority_caps(text: str) -> dict[str, int]:
    """``"r1=10,r2=5"`` -> ``{"r1": 10, "r2": 5}`` (``scmr certs --priority-cap``)."""
    out: dict[str, int] = {}
    for item in (i.strip() for i in str(text).split(",")):
        if not item:
            continue
        name, sep, value = item.partition("=")
        try:
            cap = int(value)
        except ValueError:
            cap = -1
        if not sep or not 0 <= cap <= MAX_PRIORITY:
            raise InputError(f"--priority-cap {item!r}: give NAME=P with 0 <= P <= {MAX_PRIORITY}, e.g. r1=10")
        out[name.strip()] = cap
    return out


def _write_secret(path: Path, text: str | bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(text.encode() if isinstance(text, str) else text)


def _x509():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError as exc:  # pragma: no cover - a pinned dependency
        raise ConfigError(f"the `cryptography` package is missing ({exc}); reinstall scmr-mesh "
                          "(pip install -e .) to create certificates") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _validity(days: int):
    import datetime as dt

    now = dt.datetime.now(dt.timezone.utc)
    # a minute of slack for clocks of other hosts that run slightly behind
    return now - dt.timedelta(minutes=1), now + dt.timedelta(days=days)


def _make_ca(out: Path, *, days: int):
    """Write ``ca.pem`` and ``ca.key`` (EC P-256, self-signed); return ``(cert, key)``."""
    x509, hashes, serialization, ec, _eku, NameOID = _x509()
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "scmr-mesh development CA")])
    start, end = _validity(days)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                     crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_secret(out / "ca.key", key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                    serialization.NoEncryption()))
    (out / "ca.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert, key


def _san_entries(peer: Peer, hosts: Sequence[str]):
    import ipaddress

    x509 = _x509()[0]
    names: list[str] = list(dict.fromkeys([peer.name, "localhost", "127.0.0.1", "::1", *hosts]))
    out = []
    for h in names:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            out.append(x509.DNSName(h))
    return out


def _make_peer_cert(out: Path, peer: Peer, ca, *, days: int, hosts: Sequence[str]) -> None:
    """Write ``<peer>/cert.pem`` and ``<peer>/key.pem``: CN = name, OU = role, signed by the CA."""
    x509, hashes, serialization, ec, EKU, NameOID = _x509()
    ca_cert, ca_key = ca
    pdir = out / peer.name
    pdir.mkdir(exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([
        x509.NameAttribute(NameOID.COMMON_NAME, peer.name),
        x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, peer.role),
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, "scmr-mesh"),
    ])
    start, end = _validity(days)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject).issuer_name(ca_cert.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=True,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                     crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
        .add_extension(x509.SubjectAlternativeName(_san_entries(peer, hosts)), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_secret(pdir / "key.pem", key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                      serialization.NoEncryption()))
    (pdir / "cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def create_credentials(
    out: str | Path,
    peers: str | Sequence[str] | Sequence[Peer],
    *,
    days: int = 365,
    hosts: Sequence[str] = (),
    force: bool = False,
    progress=None,
    priority: Mapping[str, int] | None = None,
    default_priority_cap: int | None = 0,
) -> Fleet:
    """Create a development CA, per-peer certificates and passwords in ``out``.

    Parameters
    ----------
    out : str or Path
        Directory to write (created; must be empty or absent unless ``force``).
    peers : str or sequence
        ``"cloud,leader,robot1"``, a list of such names, or :class:`Peer` objects.
    days : int, keyword-only
        Certificate validity in days.
    hosts : sequence of str, keyword-only
        Extra host names or IP addresses to put in every certificate's subjectAltName
        (127.0.0.1, ::1, localhost and the peer name are always there).
    force : bool, keyword-only
        Overwrite an existing credentials directory.
    progress : callable, optional
        Called with a short message per step (the CLI prints it on stderr).
    priority, default_priority_cap : keyword-only
        Priority caps of the robots (see :func:`parse_peers`); ignored when ``peers``
        are :class:`Peer` objects.

    Returns
    -------
    Fleet
        The peers and roles written to ``out/fleet.json``.

    Raises
    ------
    InputError
        Bad peer list or ``days``.
    ConfigError
        ``out`` already holds credentials (without ``force``) or a certificate could not be made.
    """
    if days < 1:
        raise InputError(f"--days must be at least 1, got {days}")
    items = [peers] if isinstance(peers, str) else list(peers)
    if items and all(isinstance(p, Peer) for p in items):
        plist: list[Peer] = items  # type: ignore[assignment]
    else:
        plist = parse_peers(",".join(str(i) for i in items), priority=priority,
                            default_priority_cap=default_priority_cap)
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; give a directory path")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ConfigError(
            f"--out {out} is not empty; choose a new directory or pass --force to overwrite"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    final, out = out, Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        fleet = _create(out, plist, days=days, hosts=hosts, say=progress or (lambda msg: None))
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    # all or nothing: the directory appears only when every file is written
    if final.exists():
        shutil.rmtree(final)
    os.replace(out, final)
    os.chmod(final, 0o755)
    log.info("wrote credentials for %d peers to %s", len(plist), final)
    return Fleet(fleet.peers, final)


def _create(out: Path, plist: list[Peer], *, days: int, hosts: Sequence[str], say) -> Fleet:
    say("creating the development CA")
    ca = _make_ca(out, days=days)
    passwords: dict[str, str] = {}
    for i, peer in enumerate(plist, 1):
        say(f"[{i}/{len(plist)}] certificate for {peer.name} ({peer.role})")
        _make_peer_cert(out, peer, ca, days=days, hosts=hosts)
        passwords[peer.name] = secrets.token_urlsafe(18)
    for peer in plist:
        pdir = out / peer.name
        _write_secret(pdir / "password", passwords[peer.name] + "\n")
        # A server checks every identity; a robot only accepts links from servers, so a
        # stolen robot's files hold no other robot's password.
        accepted = [p for p in plist if peer.is_server or p.is_server or p.name == peer.name]
        _write_secret(
            pdir / "usrpwd.txt", "".join(f"{p.name}:{passwords[p.name]}\n" for p in accepted)
        )
    fleet = Fleet(tuple(plist), out)
    (out / FLEET_FILE).write_text(
        json.dumps(
            {"version": FLEET_VERSION, "peers": [p.to_json() for p in plist]},
            indent=2,
        )
        + "\n"
    )
    return fleet


def load_fleet(directory: str | Path) -> Fleet:
    """Read ``fleet.json`` from a credentials directory made by :func:`create_credentials`.

    Raises
    ------
    ConfigError
        The directory or file is missing or malformed (names the file, the field and the fix).
    """
    d = Path(directory)
    path = d / FLEET_FILE
    if not path.is_file():
        raise ConfigError(
            f"{path} not found: {d} is not a credentials directory; create one with "
            f"`scmr certs --out {d} --peers cloud,leader,robot1,...`"
        )
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc}); re-create it with `scmr certs`") from exc
    if not isinstance(data, dict) or data.get("version") not in (1, FLEET_VERSION):
        raise ConfigError(
            f"{path}: field 'version' is {data.get('version') if isinstance(data, dict) else data!r}, "
            f"expected {FLEET_VERSION}; re-create the directory with `scmr certs`"
        )
    v1 = data["version"] == 1  # roles only: no lead grants beyond the leader, no priority caps
    raw = data.get("peers")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{path}: field 'peers' must be a non-empty list; re-create it with `scmr certs`")
    peers = []
    for i, item in enumerate(raw):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str) or item.get("role") not in ROLES:
            raise ConfigError(
                f"{path}: peers[{i}] is {item!r}; each entry needs a 'name' and a 'role' in {ROLES}"
            )
        if not NAME_RE.match(item["name"]):
            raise ConfigError(f"{path}: peers[{i}].name {item['name']!r} is not a valid peer name")
        capable = item.get("leader_capable", False)
        cap = item.get("priority_cap")
        if not isinstance(capable, bool) or not (cap is None or (isinstance(cap, int) and not isinstance(cap, bool)
                                                                 and 0 <= cap <= MAX_PRIORITY)):
            raise ConfigError(f"{path}: peers[{i}] is {item!r}; 'leader_capable' must be true or false and "
                              f"'priority_cap' an integer 0..{MAX_PRIORITY}; re-create it with `scmr certs`")
        peers.append(Peer(item["name"], item["role"], leader_capable=capable or item["role"] == "leader",
                          priority_cap=None if v1 else cap))
    return Fleet(tuple(peers), d)


@dataclass(frozen=True)
class PeerFiles:
    """Paths of one peer's credential files inside a credentials directory."""

    name: str
    ca: Path
    cert: Path
    key: Path
    password_file: Path
    dictionary: Path

    def password(self) -> str:
        """The peer's usrpwd password (read from its file)."""
        return self.password_file.read_text().strip()


def peer_files(directory: str | Path, name: str, *, need: Iterable[str] = ("ca", "cert", "key")) -> PeerFiles:
    """Locate ``name``'s files in a credentials directory and check that ``need`` exist.

    Raises
    ------
    ConfigError
        A needed file is missing (names the file and how to create it).
    """
    d = Path(directory)
    files = PeerFiles(
        name=name,
        ca=d / "ca.pem",
        cert=d / name / "cert.pem",
        key=d / name / "key.pem",
        password_file=d / name / "password",
        dictionary=d / name / "usrpwd.txt",
    )
    for attr in need:
        p: Path = getattr(files, attr)
        if not p.is_file():
            raise ConfigError(
                f"credential file {p} for peer {name!r} is missing; create it with "
                f"`scmr certs --out {d} --peers ...,{name}`"
            )
    return files
