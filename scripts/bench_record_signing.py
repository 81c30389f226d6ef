"""Per-record cost of telemetry signing (issue #28 item 3): digest, sign (robot), verify (cloud).

    PYTHONPATH=. python scripts/bench_record_signing.py [N]

Makes throw-away credentials, N (default 1000) records like a robot's, and prints microseconds per
record for each step and the bytes a signature adds on the wire.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

from scmr_mesh.data.record import encode_records, make_record
from scmr_mesh.data.signing import RecordSigner, RecordVerifier
from scmr_mesh.security.credentials import create_credentials


def main(n: int = 1000) -> None:
    with tempfile.TemporaryDirectory() as d:
        creds = Path(d) / "certs"
        create_credentials(creds, "c1=cloud,r1=robot")
        signer, verifier = RecordSigner(creds / "r1" / "key.pem"), RecordVerifier(creds)
        recs = [make_record("r1", s, pose=(1.0, 2.0, 0.5), battery=0.8, inc=12345,
                            results={"requests": s, "succeeded": s, "last_tor_ms": 41.5, "last_tier": "cloud"})
                for s in range(1, n + 1)]
        t0 = time.perf_counter()
        digests = [r.digest() for r in recs]
        t1 = time.perf_counter()
        sigs = [signer.sign(x) for x in digests]
        t2 = time.perf_counter()
        bad = sum(verifier.check("r1", x, s) is not None for x, s in zip(digests, sigs))
        t3 = time.perf_counter()
        signed = [dataclasses.replace(r, sig=s) for r, s in zip(recs, sigs)]
        plain = [dataclasses.replace(r, inc=0) for r in recs]
        extra = (len(encode_records(signed)) - len(encode_records(plain))) / n
        print(f"{n} records: digest {1e6 * (t1 - t0) / n:.1f} us, sign {1e6 * (t2 - t1) / n:.1f} us, "
              f"verify {1e6 * (t3 - t2) / n:.1f} us per record; +{extra:.0f} bytes per record on the wire "
              f"(signature and incarnation); {bad} failed verification")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000)
