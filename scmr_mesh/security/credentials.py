"""Development credentials for an authenticated mesh: a CA, per-peer certificates, passwords.

``scmr certs --out DIR --peers cloud,leader,robot1`` calls :func:`create_credentials`,
which writes::

    DIR/ca.pem, DIR/ca.key            development certificate authority (keep ca.key offline)
    DIR/<peer>/cert.pem, key.pem      the peer's certificate (CN = peer name) and private key
    DIR/<peer>/password               the peer's usrpwd password (the lighter option)
    DIR/<peer>/usrpwd.txt             the usrpwd dictionary this peer checks incoming links against
    DIR/fleet.json                    peer names and roles (cloud, leader, robot): the ACL's input

Certificates are made with the ``openssl`` command-line tool (no extra Python package).
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
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

from scmr_mesh.errors import ConfigError, InputError

log = logging.getLogger(__name__)

#: Roles a peer may have.  ``cloud`` and ``leader`` are servers (they may serve
#: ``scmr/drivable/**`` and read the data store); ``robot`` is a client.
ROLES: tuple[str, ...] = ("cloud", "leader", "robot")
SERVER_ROLES: frozenset[str] = frozenset({"cloud", "leader"})

#: Peer names double as certificate common names, usrpwd user names and key-expression
#: chunks, so they are restricted to a safe alphabet.
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,62}$")

FLEET_FILE = "fleet.json"
FLEET_VERSION = 1


@dataclass(frozen=True)
class Peer:
    """One identity of the mesh.

    Parameters
    ----------
    name : str
        Peer name: certificate CN, usrpwd user name and node id (``robot1``).
    role : str
        One of :data:`ROLES`.
    """

    name: str
    role: str

    @property
    def is_server(self) -> bool:
        """True for cloud and leader identities."""
        return self.role in SERVER_ROLES


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
        """Names of the cloud and leader identities."""
        return [p.name for p in self.peers if p.is_server]

    @property
    def robots(self) -> list[str]:
        """Names of the robot identities."""
        return [p.name for p in self.peers if not p.is_server]

    def get(self, name: str) -> Peer:
        """The peer called ``name``; :class:`ConfigError` if there is none."""
        for p in self.peers:
            if p.name == name:
                return p
        where = f" in {self.directory / FLEET_FILE}" if self.directory else ""
        raise ConfigError(
            f"no credentials for peer {name!r}{where} (known: {', '.join(self.names())}); "
            f"re-run `scmr certs --peers ...` including {name!r}"
        )


def infer_role(name: str) -> str:
    """Role from a peer name: ``cloud*`` -> cloud, ``leader*`` -> leader, anything else robot."""
    low = name.lower()
    if low.startswith("cloud"):
        return "cloud"
    if low.startswith("leader"):
        return "leader"
    return "robot"


def parse_peers(spec: str | Sequence[str]) -> list[Peer]:
    """Parse ``"cloud,leader,robot1,edge=cloud"`` into peers.

    A bare name gets its role from :func:`infer_role`; ``name=role`` sets it explicitly.

    Raises
    ------
    InputError
        On an empty list, a bad name, an unknown role or a duplicate.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    items = [i.strip() for i in items if i.strip()]
    if not items:
        raise InputError("--peers is empty; give names such as --peers cloud,leader,robot1,robot2")
    peers: list[Peer] = []
    seen: set[str] = set()
    for item in items:
        name, _, role = item.partition("=")
        name, role = name.strip(), (role.strip() or infer_role(name.strip()))
        if not NAME_RE.match(name):
            raise InputError(
                f"peer name {name!r} is not allowed: use 1-63 letters, digits, '-' or '_', "
                "starting with a letter or digit (for example robot1)"
            )
        if role not in ROLES:
            raise InputError(f"peer {name!r} has role {role!r}; use one of {', '.join(ROLES)}")
        if name in seen:
            raise InputError(f"peer {name!r} is listed twice in --peers; list each peer once")
        seen.add(name)
        peers.append(Peer(name, role))
    if not any(p.is_server for p in peers):
        log.warning("no cloud or leader identity in %s: nobody will be allowed to serve", items)
    return peers


def _openssl() -> str:
    exe = shutil.which("openssl")
    if exe is None:
        raise ConfigError(
            "the `openssl` command was not found on PATH; install it (apt-get install openssl) "
            "to create certificates"
        )
    return exe


def _run(args: list[str], *, cwd: Path) -> None:
    proc = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=60)
    if proc.returncode != 0:
        raise ConfigError(
            f"openssl failed ({' '.join(args[:3])} ...): {proc.stderr.strip()[-400:]}"
        )


def _write_secret(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)


def _make_ca(out: Path, *, days: int) -> None:
    _run(
        [
            _openssl(), "req", "-x509", "-new", "-newkey", "ec",
            "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-sha256",
            "-keyout", "ca.key", "-out", "ca.pem", "-days", str(days),
            "-subj", "/CN=scmr-mesh development CA",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        ],
        cwd=out,
    )
    os.chmod(out / "ca.key", 0o600)


def _make_peer_cert(out: Path, peer: Peer, *, days: int, hosts: Sequence[str]) -> None:
    pdir = out / peer.name
    pdir.mkdir(exist_ok=True)
    sans = [f"DNS:{peer.name}", "DNS:localhost", "IP:127.0.0.1", "IP:::1"]
    for h in hosts:
        sans.append(f"IP:{h}" if re.fullmatch(r"[0-9.]+|[0-9a-fA-F:]+:[0-9a-fA-F:]*", h) else f"DNS:{h}")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        (t / "ext.cnf").write_text(
            "basicConstraints=critical,CA:FALSE\n"
            "keyUsage=critical,digitalSignature,keyEncipherment\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
            f"subjectAltName={','.join(dict.fromkeys(sans))}\n"
        )
        _run(
            [
                _openssl(), "req", "-new", "-newkey", "ec",
                "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                "-keyout", str(pdir / "key.pem"), "-out", str(t / "req.csr"),
                "-subj", f"/CN={peer.name}/OU={peer.role}/O=scmr-mesh",
            ],
            cwd=out,
        )
        _run(
            [
                _openssl(), "x509", "-req", "-in", str(t / "req.csr"), "-CA", "ca.pem",
                "-CAkey", "ca.key", "-CAcreateserial", "-sha256", "-days", str(days),
                "-out", str(pdir / "cert.pem"), "-extfile", str(t / "ext.cnf"),
            ],
            cwd=out,
        )
    os.chmod(pdir / "key.pem", 0o600)


def create_credentials(
    out: str | Path,
    peers: str | Sequence[str] | Sequence[Peer],
    *,
    days: int = 365,
    hosts: Sequence[str] = (),
    force: bool = False,
    progress=None,
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

    Returns
    -------
    Fleet
        The peers and roles written to ``out/fleet.json``.

    Raises
    ------
    InputError
        Bad peer list or ``days``.
    ConfigError
        ``out`` already holds credentials (without ``force``) or openssl failed.
    """
    if days < 1:
        raise InputError(f"--days must be at least 1, got {days}")
    items = [peers] if isinstance(peers, str) else list(peers)
    if items and all(isinstance(p, Peer) for p in items):
        plist: list[Peer] = items  # type: ignore[assignment]
    else:
        plist = parse_peers(",".join(str(i) for i in items))
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
    _make_ca(out, days=days)
    passwords: dict[str, str] = {}
    for i, peer in enumerate(plist, 1):
        say(f"[{i}/{len(plist)}] certificate for {peer.name} ({peer.role})")
        _make_peer_cert(out, peer, days=days, hosts=hosts)
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
            {"version": FLEET_VERSION, "peers": [{"name": p.name, "role": p.role} for p in plist]},
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
    if not isinstance(data, dict) or data.get("version") != FLEET_VERSION:
        raise ConfigError(
            f"{path}: field 'version' is {data.get('version') if isinstance(data, dict) else data!r}, "
            f"expected {FLEET_VERSION}; re-create the directory with `scmr certs`"
        )
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
        peers.append(Peer(item["name"], item["role"]))
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
