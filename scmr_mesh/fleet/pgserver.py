"""A PostgreSQL server of our own, in a directory of the run (Debian's ``postgresql`` package).

``scmr up --clouds N`` (N > 1), ``scmr bench scale`` and the tests start one so
that several cloud nodes share one operational data store.  Nothing is
installed by hand: ``make`` / ``.ci/run`` install the ``postgresql`` package
when ``initdb`` is missing; the binaries are found on ``PATH`` or under
``/usr/lib/postgresql/<version>/bin``.

The server runs as a child process (``postgres -D DIR``, not daemonised by
``pg_ctl``), listening on a Unix socket in a directory of its own (no TCP port
unless asked, so parallel runs never collide), with ``trust`` authentication
for the local socket only.  It dies with the thread that started it
(``PR_SET_PDEATHSIG``), so a SIGKILLed launcher leaves no server behind.
PostgreSQL refuses to run as root: as root the cluster is created and run as
the ``postgres`` user (else ``nobody``) and the data directory is made theirs.

Example
-------
>>> import tempfile
>>> with PgServer(tempfile.mkdtemp()) as pg:          # doctest: +SKIP
...     dsn = pg.dsn                                   # postgresql://scmr@/scmr?host=...
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import logging
import os
import pwd
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from scmr_mesh import deathsig
from scmr_mesh.errors import InputError

log = logging.getLogger(__name__)

#: Database and role the ODS uses on a server we start.
DB_NAME = "scmr"
DB_USER = "scmr"
#: Longest Unix socket directory (sun_path is 108 bytes with ``/.s.PGSQL.NNNNN``).
_MAX_SOCKET_DIR = 90

INSTALL_HINT = "install Debian's postgresql package (apt-get install -y postgresql; `make` does it)"


class PgServerError(InputError):
    """The PostgreSQL server could not be found, created or started (the message says why and the fix)."""


def find_bin(name: str) -> str | None:
    """Path of a PostgreSQL program: ``PATH`` first, then the newest ``/usr/lib/postgresql/*/bin``."""
    p = shutil.which(name)
    if p:
        return p
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"),
                   key=lambda s: [int(x) if x.isdigit() else 0 for x in s.split("/")[4].split(".")])
    return found[-1] if found else None


def available() -> str | None:
    """Why a server cannot be started here (None when ``initdb`` and ``postgres`` are present)."""
    missing = [n for n in ("initdb", "postgres") if find_bin(n) is None]
    if missing:
        return f"PostgreSQL programs not found ({', '.join(missing)}); {INSTALL_HINT}"
    return None


def _server_user() -> str | None:
    """The unprivileged user to run the server as when we are root (None when we are not root)."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            pwd.getpwnam(name)
            return name
        except KeyError:
            continue
    raise PgServerError("running as root, and neither a 'postgres' nor a 'nobody' user exists to run "
                        "PostgreSQL (it refuses root); create a postgres user or run as a normal user")


def _as_user(user: str | None) -> dict:
    if user is None:
        return {}
    pw = pwd.getpwnam(user)
    return {"user": pw.pw_uid, "group": pw.pw_gid, "extra_groups": []}


def _reachable(path: Path, user: str | None) -> bool:
    """Whether ``user`` can enter every folder down to ``path`` (always True for ourselves)."""
    if user is None:
        return True
    pw = pwd.getpwnam(user)
    p = path.resolve()
    for d in [*reversed(p.parents), p]:
        st = d.stat()
        if st.st_uid == pw.pw_uid:
            ok = st.st_mode & 0o100
        elif st.st_gid == pw.pw_gid:
            ok = st.st_mode & 0o010
        else:
            ok = st.st_mode & 0o001
        if not ok:
            return False
    return True


class PgServer:
    """One PostgreSQL cluster and server process under ``root``.

    Parameters
    ----------
    root : path
        Folder for the cluster (``root/pgdata``), its log (``root/postgres.log``)
        and, when the path is short enough, its socket (``root/socket``).  When
        we run as root and the server's user cannot enter ``root``, the cluster
        goes to a fresh ``/tmp/scmr-pg-*`` folder instead (logged; :attr:`root`
        says where).
    port : int
        The socket's number (``.s.PGSQL.<port>``); also the TCP port with ``listen``.
    listen : str, optional
        Also accept TCP connections on this address (e.g. ``127.0.0.1``;
        authentication ``trust`` from loopback only).  Default: the Unix socket only.
    trust : tuple of str
        More client networks (CIDR) trusted over TCP, e.g. another site's link.
        A real deployment uses ``scram-sha-256`` and TLS instead (docs/DEPLOY.md).
    prefix : tuple of str
        Command prefix of the server and its probes, e.g. ``("ip", "netns",
        "exec", NS)`` to run it inside a network namespace (as root the server
        is then started through ``runuser``).
    """

    def __init__(self, root: str | Path, *, port: int = 5432, listen: str | None = None,
                 trust: tuple[str, ...] = (), prefix: tuple[str, ...] = ()) -> None:
        why = available()
        if why:
            raise PgServerError(why)
        self.user = _server_user()
        self.port = int(port)
        self.listen = listen
        self.trust = tuple(trust)
        self.prefix = tuple(prefix)
        root = Path(root).resolve()
        root.mkdir(parents=True, exist_ok=True)
        self._own_root = False
        if not _reachable(root, self.user):
            tmp = Path(tempfile.mkdtemp(prefix="scmr-pg-"))
            pw = pwd.getpwnam(self.user)
            os.chown(tmp, pw.pw_uid, pw.pw_gid)
            log.warning("PostgreSQL runs as %r, which cannot enter %s; its cluster goes to %s instead",
                        self.user, root, tmp)
            root, self._own_root = tmp, True
        self.root = root
        self.data_dir = root / "pgdata"
        self.log_path = root / "postgres.log"
        sock = root / "socket"
        self._own_sock = False
        if len(str(sock)) > _MAX_SOCKET_DIR:
            sock = Path(tempfile.mkdtemp(prefix="scmr-pgs-"))
            self._own_sock = True
        self.socket_dir = sock
        self.proc: subprocess.Popen | None = None

    # ------------------------------------------------------------------ addresses
    @property
    def dsn(self) -> str:
        """``postgresql://scmr@/scmr?host=<socket dir>&port=<port>`` (or the TCP address with ``listen``)."""
        return self.dsn_for(DB_NAME)

    def dsn_for(self, db: str) -> str:
        """The URL of database ``db`` on this server."""
        if self.listen:
            return f"postgresql://{DB_USER}@{self.listen}:{self.port}/{db}"
        return f"postgresql://{DB_USER}@/{db}?host={self.socket_dir}&port={self.port}"

    # ------------------------------------------------------------------ life cycle
    def _chown(self, path: Path) -> None:
        if self.user is not None:
            pw = pwd.getpwnam(self.user)
            os.chown(path, pw.pw_uid, pw.pw_gid)

    def init(self) -> None:
        """``initdb`` the cluster unless it exists (superuser ``scmr``, trust on the local socket)."""
        if (self.data_dir / "PG_VERSION").is_file():
            return
        self.data_dir.mkdir(mode=0o700, exist_ok=True)
        self._chown(self.data_dir)
        cmd = [find_bin("initdb"), "-D", str(self.data_dir), "-U", DB_USER, "--auth-local=trust",
               "--auth-host=trust" if self.listen else "--auth-host=reject", "-E", "UTF8", "--no-locale",
               "--no-sync"]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, **_as_user(self.user))
        if r.returncode != 0:
            last = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["no output"]
            raise PgServerError(f"initdb {self.data_dir} failed (exit {r.returncode}): {last[0]}")
        if self.listen:  # only loopback clients (and the networks in ``trust``) are trusted
            hba = self.data_dir / "pg_hba.conf"
            hba.write_text("local all all trust\nhost all all 127.0.0.1/32 trust\nhost all all ::1/128 trust\n"
                           + "".join(f"host all all {net} trust\n" for net in self.trust))

    def start(self, *, timeout: float = 60.0) -> str:
        """Create the cluster if needed, start the server, create the database; return :attr:`dsn`.

        Raises
        ------
        PgServerError
            The server exited or did not accept connections within ``timeout``
            (the message ends with the last line of its log).
        """
        if self.proc is not None and self.proc.poll() is None:
            return self.dsn
        self.init()
        self.socket_dir.mkdir(exist_ok=True)
        self._chown(self.socket_dir)
        settings = {
            "listen_addresses": self.listen or "",
            "port": str(self.port),
            "unix_socket_directories": str(self.socket_dir),
            "max_connections": "200",
            "shared_buffers": "32MB",
            "logging_collector": "off",
        }
        argv = [find_bin("postgres"), "-D", str(self.data_dir)]
        for k, v in settings.items():
            argv += ["-c", f"{k}={v}"]
        as_user = _as_user(self.user)
        if self.prefix:  # e.g. ip netns exec NS: root switches namespace, then runuser drops to the user
            argv = [*self.prefix, *(["runuser", "-u", self.user, "--"] if self.user else []), *argv]
            as_user = {}
        with open(self.log_path, "ab") as logf:
            if self.user is not None:
                self._chown(self.log_path)
            # SIGKILL the server when the starting thread dies; subprocess switches to the server's
            # user *before* calling preexec_fn, so the death signal survives (a credential change
            # would clear it)
            self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT,
                                         start_new_session=True, preexec_fn=deathsig.preexec(signal.SIGKILL),
                                         close_fds=True, **as_user)
        self._wait_ready(timeout)
        self._create_db()
        log.info("PostgreSQL %s serving %s (pid %d)", self.data_dir, self.dsn, self.proc.pid)
        return self.dsn

    def _last_log_line(self) -> str:
        try:
            lines = [ln for ln in self.log_path.read_text(errors="replace").splitlines() if ln.strip()]
        except OSError:
            return "(no log)"
        return lines[-1] if lines else "(empty log)"

    def _psql(self, db: str, sql: str) -> subprocess.CompletedProcess:
        host = self.listen or str(self.socket_dir)
        return subprocess.run([*self.prefix, find_bin("psql"), "-X", "-q", "-h", host, "-p", str(self.port), "-U", DB_USER,
                               "-d", db, "-v", "ON_ERROR_STOP=1", "-tA", "-c", sql],
                              capture_output=True, text=True, timeout=30)

    def _wait_ready(self, timeout: float) -> None:
        isready = find_bin("pg_isready")
        host = self.listen or str(self.socket_dir)
        end = time.monotonic() + timeout
        while True:
            rc = self.proc.poll()
            if rc is not None:
                raise PgServerError(f"PostgreSQL exited with status {rc} at start; {self.log_path}: "
                                    f"{self._last_log_line()}")
            r = subprocess.run([*self.prefix, isready, "-q", "-h", host, "-p", str(self.port)], capture_output=True,
                               timeout=10)
            if r.returncode == 0:
                return
            if time.monotonic() > end:
                self.stop()
                raise PgServerError(f"PostgreSQL did not accept connections within {timeout:g} s; "
                                    f"{self.log_path}: {self._last_log_line()}")
            time.sleep(0.05)

    def _create_db(self) -> None:
        r = self._psql("postgres", f"SELECT 1 FROM pg_database WHERE datname = '{DB_NAME}'")
        if r.returncode == 0 and r.stdout.strip() == "1":
            return
        r = self._psql("postgres", f"CREATE DATABASE {DB_NAME}")
        if r.returncode != 0 and "already exists" not in r.stderr:
            raise PgServerError(f"cannot create database {DB_NAME!r}: {r.stderr.strip().splitlines()[-1:]}")

    def create_database(self, name: str) -> str:
        """Create an empty database ``name`` (letters, digits, ``_``) on the running server; return its URL."""
        if not re.fullmatch(r"[a-z_][a-z0-9_]{0,62}", name):
            raise PgServerError(f"database name must be lower-case letters, digits and _, got {name!r}")
        r = self._psql("postgres", f"CREATE DATABASE {name}")
        if r.returncode != 0:
            raise PgServerError(f"cannot create database {name!r}: {r.stderr.strip()}")
        return self.dsn_for(name)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, *, timeout: float = 30.0) -> int | None:
        """Fast shutdown (SIGINT: roll back open transactions, close clients); SIGKILL after ``timeout``."""
        p, self.proc = self.proc, None
        if p is None:
            return None
        if p.poll() is None:
            try:
                if self.prefix:  # the postmaster is a grandchild (runuser): signal the group
                    os.killpg(p.pid, signal.SIGINT)
                else:
                    p.send_signal(signal.SIGINT)
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                log.warning("PostgreSQL ignored a fast shutdown for %.0f s; SIGKILL", timeout)
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        try:  # backends left in the group
            os.killpg(p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        if self._own_sock:  # a /tmp/scmr-pgs-* folder of ours (the root's path was too long): empty now
            shutil.rmtree(self.socket_dir, ignore_errors=True)
        return p.returncode

    def remove(self) -> None:
        """Stop the server and delete the cluster and its socket folder."""
        self.stop()
        shutil.rmtree(self.data_dir, ignore_errors=True)
        shutil.rmtree(self.socket_dir, ignore_errors=True)
        if self._own_root:
            shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> "PgServer":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


__all__ = ["DB_NAME", "DB_USER", "PgServer", "PgServerError", "available", "find_bin", "run_store"]



def _exists(path: Path) -> bool:
    """Whether ``path`` exists, also when we may not look inside its folder (then: the folder exists)."""
    try:
        return path.exists()
    except PermissionError:
        return path.parent.is_dir()


def _report_ods(run_dir: Path) -> dict:
    """The ``ods`` block of ``RUN/report.json`` (``{"backend", "store"}``), or ``{}``."""
    import json

    try:
        ods = json.loads((run_dir / "report.json").read_text()).get("ods")
    except (OSError, ValueError, AttributeError):
        return {}
    return ods if isinstance(ods, dict) else {}


def _live_url(socket_dir: Path) -> str | None:
    """The URL of a server answering on a socket in ``socket_dir`` (``pg_isready``), or None."""
    isready = find_bin("pg_isready")
    try:
        socks = sorted(socket_dir.glob(".s.PGSQL.*"))
    except OSError:
        return None
    for sock in socks:
        port = sock.name.rsplit(".", 1)[-1]
        if not port.isdigit() or isready is None:
            continue
        r = subprocess.run([isready, "-q", "-h", str(socket_dir), "-p", port], capture_output=True, timeout=10)
        if r.returncode == 0:
            return f"postgresql://{DB_USER}@/{DB_NAME}?host={socket_dir}&port={port}"
    return None


@contextlib.contextmanager
def run_store(run_dir: str | Path):
    """The data store of a run folder (``scmr up``/``demo``/``scenario``), for ``scmr ods --db RUN``.

    Yields ``RUN/ods.sqlite`` when the run kept one (and its report does not
    name PostgreSQL); else the URL of the run's PostgreSQL cluster in
    ``RUN/postgres``: its running server's, or that of a server started on it
    for the duration of the ``with`` block and stopped after.  Queries of one
    run folder are serialised by a lock file (``RUN/postgres/.scmr-ods.lock``),
    so one never stops a server another is reading.

    Raises
    ------
    InputError
        The folder holds no store, its store was elsewhere, or its cluster
        cannot be started by this user (one line naming the owner and the fix).
    """
    run_dir = Path(run_dir)
    ods = _report_ods(run_dir)
    store = str(ods.get("store") or "")
    sqlite = run_dir / "ods.sqlite"
    pg_root = run_dir / "postgres"
    data_dir = pg_root / "pgdata"
    has_pg = _exists(data_dir / "PG_VERSION")
    if sqlite.is_file() and not (has_pg and ods.get("backend") == "postgresql"):
        yield sqlite, None
        return
    if not has_pg:
        if ods.get("backend") == "postgresql" and "scmr-pg" in store:
            raise InputError(f"the PostgreSQL store of {run_dir} is gone: its cluster was outside the run folder "
                             "(PostgreSQL's user could not enter it) and was removed with the run; run the fleet "
                             "under a folder that user can enter to keep it")
        if store and ods.get("backend") in ("postgresql", "sqlite"):
            raise InputError(f"{run_dir} used the {ods['backend']} store {store}; pass it with --db")
        raise InputError(f"{run_dir} holds no data store (no ods.sqlite, no postgres/pgdata); pass the folder "
                         "of a run (scmr up/demo/scenario), an ODS file or a postgresql:// URL")
    try:
        lock = open(pg_root / ".scmr-ods.lock", "a")
    except OSError:
        lock = None  # not ours to write: we can only read a server that is running
    try:
        if lock is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
        url = _live_url(pg_root / "socket")
        if url is not None:
            yield url, None
            return
        owner = data_dir.stat().st_uid
        user = _server_user()
        uid = pwd.getpwnam(user).pw_uid if user else os.geteuid()
        if owner != uid or lock is None:
            try:
                name = pwd.getpwuid(owner).pw_name
            except KeyError:
                name = str(owner)
            raise InputError(f"the PostgreSQL cluster of {run_dir} is stopped and belongs to user {name!r}; "
                             f"run `scmr ods` as root or as {name} to start it, or pass the URL of a running "
                             "server with --db")
        server = PgServer(pg_root)
        if server.root != pg_root.resolve():
            server.remove()
            raise InputError(f"PostgreSQL's user {server.user!r} cannot enter {pg_root}; give it access "
                             f"(chmod o+x on each parent folder) or copy the run somewhere it can")
        try:
            server.start()
            yield server.dsn, server
        finally:
            server.stop()
    finally:
        if lock is not None:
            lock.close()  # releases the lock
