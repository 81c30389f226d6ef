"""Telemetry records signed by the robot that made them, verified by the store (issue #28 item 3).

A relay (the leader, or any identity the ACL lets query the cloud's relay key)
forwards other robots' records; the access-control rules alone cannot tell a
forwarded record from a made-up one.  So each robot signs every record's
:func:`~scmr_mesh.data.record.record_digest` with its own private key (ECDSA
P-256, the key of its TLS certificate, ``<credentials>/<robot>/key.pem``), and
the store verifies the signature with the robot's certificate
(``<credentials>/<robot>/cert.pem``, which must be issued by the fleet's CA
``ca.pem`` for common name ``<robot>`` and be valid now).  A record whose
signature is missing or wrong is refused on its own (the rest of its batch is
stored) and counted.

Pure: the ``cryptography`` package only; nothing here touches the mesh.
"""

from __future__ import annotations

import datetime
import re
import threading
import time
from pathlib import Path

from scmr_mesh.data.errors import TelemetryError

#: A robot name as a key chunk (``keys.check_name``): never a path of its own.
_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}")


def _crypto():
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec, utils
    from cryptography.x509.oid import NameOID

    return x509, InvalidSignature, hashes, serialization, ec, utils, NameOID


class RecordSigner:
    """Signs record digests with one robot's private key.

    Parameters
    ----------
    key_path : path
        The robot's PEM private key (``<credentials>/<robot>/key.pem``).
    """

    def __init__(self, key_path: str | Path) -> None:
        _, _, _, serialization, ec, utils, _ = _crypto()
        try:
            self._key = serialization.load_pem_private_key(Path(key_path).read_bytes(), password=None)
        except (OSError, ValueError, TypeError) as exc:
            raise TelemetryError(f"cannot load the record signing key {key_path} ({exc}); make the fleet's "
                                 "credentials with `scmr certs`") from None
        if not isinstance(self._key, ec.EllipticCurvePrivateKey):
            raise TelemetryError(f"record signing key {key_path} is not an EC key; make it with `scmr certs`")
        self._alg = ec.ECDSA(utils.Prehashed(_crypto()[2].SHA256()))

    def sign(self, digest: bytes) -> bytes:
        """DER ECDSA signature of a 32-byte SHA-256 ``digest``."""
        return self._key.sign(digest, self._alg)


class RecordVerifier:
    """Checks a record's signature against its robot's certificate from the fleet's credentials.

    Certificates are loaded once per robot (checked against ``ca.pem``: issuer
    signature, common name, validity) and cached; a robot without a valid
    certificate has every record refused.  Thread-safe.

    Parameters
    ----------
    credentials : path
        A directory made by ``scmr certs`` (``ca.pem``, ``<robot>/cert.pem``).
    """

    def __init__(self, credentials: str | Path) -> None:
        self.directory = Path(credentials)
        ca = self.directory / "ca.pem"
        try:
            self._ca_pem = ca.read_bytes()
        except OSError as exc:
            raise TelemetryError(f"cannot load the fleet CA {ca} ({exc}); make the credentials with "
                                 "`scmr certs`") from None
        if b"-----BEGIN " not in self._ca_pem or b"CERTIFICATE-----" not in self._ca_pem:
            raise TelemetryError(f"cannot load the fleet CA {ca} (no PEM certificate in it); make the "
                                 "credentials with `scmr certs`")
        # parsed by warm() once the service is ready, or at the first record, not here: importing
        # cryptography's x509 cost a cloud's start 35-45 ms of CPU (docs/BENCHMARKS.md)
        self._ca = None
        self._ca_error: str | None = None
        self._ca_lock = threading.Lock()  # its own: the parse imports x509 and must not hold _lock
        self._keys: dict[str, tuple[object, datetime.datetime]] = {}
        self._misses: dict[str, float] = {}  # name -> when its lookup failed (monotonic s), oldest first
        self._lock = threading.Lock()

    def _ca_cert(self):
        """The fleet CA's certificate (parsed once), or None when it does not parse (:attr:`_ca_error`)."""
        with self._ca_lock:
            if self._ca is None and self._ca_error is None:
                x509 = _crypto()[0]
                try:
                    self._ca = x509.load_pem_x509_certificate(self._ca_pem)
                except ValueError as exc:
                    self._ca_error = (f"cannot load the fleet CA {self.directory / 'ca.pem'} ({exc}); make the "
                                      "credentials with `scmr certs`")
            return self._ca

    def warm(self) -> str | None:
        """Parse the fleet CA now (a service calls it once ready); why it does not load, or None."""
        self._ca_cert()
        return self._ca_error

    #: A name without a valid certificate is looked up again after this long (a robot enrolled
    #: later, a certificate renewed on disk); at most :attr:`MAX_MISSES` names are remembered.
    MISS_TTL_S = 5.0
    MAX_MISSES = 1024
    #: Longest robot name looked up on disk (names are key chunks: ``keys.check_name``).
    MAX_NAME = 64

    def _public_key(self, robot: str):
        """The robot's public key, or None (no valid certificate).

        Valid keys are cached with their expiry and checked on each use; misses are cached for
        :attr:`MISS_TTL_S` in a bounded table, so names a relay makes up cost neither memory
        without bound nor a file lookup per record, and a robot enrolled later is not refused
        until the cloud restarts (a review found both).
        """
        now_s = time.monotonic()
        with self._lock:
            hit = self._keys.get(robot)
            if hit is not None:
                key, not_after = hit
                if datetime.datetime.now(datetime.timezone.utc) <= not_after:
                    return key
                del self._keys[robot]  # expired: read the (perhaps renewed) certificate again
            miss = self._misses.get(robot)
            if miss is not None and now_s - miss < self.MISS_TTL_S:
                return None
        if not _NAME.fullmatch(robot or "") or len(robot) > self.MAX_NAME:
            key, not_after = None, None
        else:
            key, not_after = self._load(robot)
        with self._lock:
            if key is not None:
                self._keys[robot] = (key, not_after)
                self._misses.pop(robot, None)
            else:
                self._misses[robot] = now_s
                while len(self._misses) > self.MAX_MISSES:  # the oldest miss goes first
                    self._misses.pop(next(iter(self._misses)))
        return key

    def _load(self, robot: str):
        x509, InvalidSignature, _, _, ec, _, NameOID = _crypto()
        ca = self._ca_cert()
        if ca is None:
            return None, None
        path = self.directory / robot / "cert.pem"
        try:
            cert = x509.load_pem_x509_certificate(path.read_bytes())
            ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes,
                                         ec.ECDSA(cert.signature_hash_algorithm))
            cn = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
            now = datetime.datetime.now(datetime.timezone.utc)
            if cn == [robot] and cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
                return cert.public_key(), cert.not_valid_after_utc
        except (OSError, ValueError, TypeError, InvalidSignature):
            pass
        return None, None

    def check(self, robot: str, digest: bytes, sig: bytes | None) -> str | None:
        """None when ``sig`` is ``robot``'s signature of ``digest``, else why not (one line)."""
        if sig is None:
            return f"record of {robot} is not signed"
        key = self._public_key(robot)
        if key is None:
            return self._ca_error or f"no valid certificate for {robot} under {self.directory}"
        _, InvalidSignature, hashes, _, ec, utils, _ = _crypto()
        try:
            key.verify(sig, digest, ec.ECDSA(utils.Prehashed(hashes.SHA256())))
        except (InvalidSignature, ValueError):
            return f"record of {robot} has a signature that is not {robot}'s"
        return None


__all__ = ["RecordSigner", "RecordVerifier"]
