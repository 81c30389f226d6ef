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
import threading
from pathlib import Path

from scmr_mesh.data.errors import TelemetryError


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
        x509 = _crypto()[0]
        self.directory = Path(credentials)
        try:
            self._ca = x509.load_pem_x509_certificate((self.directory / "ca.pem").read_bytes())
        except (OSError, ValueError) as exc:
            raise TelemetryError(f"cannot load the fleet CA {self.directory / 'ca.pem'} ({exc}); make the "
                                 "credentials with `scmr certs`") from None
        self._keys: dict[str, object] = {}
        self._lock = threading.Lock()

    def _public_key(self, robot: str):
        with self._lock:
            if robot in self._keys:
                return self._keys[robot]
        x509, InvalidSignature, _, _, ec, _, NameOID = _crypto()
        path = self.directory / robot / "cert.pem"
        try:
            cert = x509.load_pem_x509_certificate(path.read_bytes())
            self._ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes,
                                         ec.ECDSA(cert.signature_hash_algorithm))
            cn = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
            now = datetime.datetime.now(datetime.timezone.utc)
            ok = cn == [robot] and cert.not_valid_before_utc <= now <= cert.not_valid_after_utc
            key = cert.public_key() if ok else None
        except (OSError, ValueError, TypeError, InvalidSignature):
            key = None
        with self._lock:
            self._keys[robot] = key  # a robot without a valid certificate: cached as None
        return key

    def check(self, robot: str, digest: bytes, sig: bytes | None) -> str | None:
        """None when ``sig`` is ``robot``'s signature of ``digest``, else why not (one line)."""
        if sig is None:
            return f"record of {robot} is not signed"
        key = self._public_key(robot)
        if key is None:
            return f"no valid certificate for {robot} under {self.directory}"
        _, InvalidSignature, hashes, _, ec, utils, _ = _crypto()
        try:
            key.verify(sig, digest, ec.ECDSA(utils.Prehashed(hashes.SHA256())))
        except (InvalidSignature, ValueError):
            return f"record of {robot} has a signature that is not {robot}'s"
        return None


__all__ = ["RecordSigner", "RecordVerifier"]
