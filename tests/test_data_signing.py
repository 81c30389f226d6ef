"""Record signatures checked against the fleet's certificates (issue 28 item 3; a review's findings)."""

from __future__ import annotations

import hashlib

import pytest

from scmr_mesh.data.signing import RecordSigner, RecordVerifier


@pytest.fixture(scope="module")
def creds(tmp_path_factory):
    from scmr_mesh.security.credentials import create_credentials

    d = tmp_path_factory.mktemp("signcreds") / "fleet"
    create_credentials(d, "cloud,robot1,robot2")
    return d


def test_made_up_names_cost_bounded_memory_and_are_never_read_as_paths(creds):
    v = RecordVerifier(creds)
    digest = hashlib.sha256(b"x").digest()
    sig = RecordSigner(creds / "robot1" / "key.pem").sign(digest)
    assert v.check("robot1", digest, sig) is None
    for i in range(3 * v.MAX_MISSES):  # a relay inventing robot names (before: each cached for good)
        assert "no valid certificate" in v.check(f"ghost{i}", digest, sig)
    assert len(v._misses) == v.MAX_MISSES and len(v._keys) == 1
    for name in ("..", "../robot1", "robot1/../robot1", "", "x" * 65):
        assert "no valid certificate" in v.check(name, digest, sig)
    assert "not robot2's" in v.check("robot2", digest, sig)  # robot1's signature claimed for robot2


def test_a_robot_enrolled_after_a_refusal_is_accepted_once_its_miss_expires(creds, tmp_path, monkeypatch):
    moved = tmp_path / "robot2"
    (creds / "robot2").rename(moved)  # robot2 not enrolled yet
    try:
        v = RecordVerifier(creds)
        digest = hashlib.sha256(b"y").digest()
        sig = RecordSigner(moved / "key.pem").sign(digest)
        assert "no valid certificate" in v.check("robot2", digest, sig)
    finally:
        moved.rename(creds / "robot2")  # now enrolled
    assert "no valid certificate" in v.check("robot2", digest, sig)  # the miss is remembered a while
    monkeypatch.setattr(RecordVerifier, "MISS_TTL_S", 0.0)
    assert v.check("robot2", digest, sig) is None  # before: refused until the cloud restarted


def test_the_fleet_ca_is_checked_at_start_and_parsed_later(creds, tmp_path, repo_root):
    import os
    import shutil
    import subprocess
    import sys

    from scmr_mesh.data.errors import TelemetryError

    # a cloud's start does not import cryptography's x509 (35-45 ms of a restart); warm() or a record does
    code = ("import sys; from scmr_mesh.data.signing import RecordVerifier; v = RecordVerifier(sys.argv[1]); "
            "a = 'cryptography.x509' in sys.modules; w = v.warm(); print(a, w, 'cryptography.x509' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(creds)], capture_output=True, text=True, check=True,
                         cwd=repo_root, env=dict(os.environ, PYTHONPATH=str(repo_root)))
    assert out.stdout.split() == ["False", "None", "True"], out
    # a missing CA, or one with no PEM certificate in it, still fails at start, in one line
    with pytest.raises(TelemetryError, match="cannot load the fleet CA .*ca.pem"):
        RecordVerifier(tmp_path)
    (tmp_path / "ca.pem").write_text("not a certificate\n")
    with pytest.raises(TelemetryError, match="no PEM certificate"):
        RecordVerifier(tmp_path)
    # a CA that looks like PEM but does not parse: warm() says why, and every record is refused saying so
    bad = tmp_path / "bad"
    shutil.copytree(creds, bad)
    (bad / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n")
    v = RecordVerifier(bad)
    digest = hashlib.sha256(b"z").digest()
    sig = RecordSigner(creds / "robot1" / "key.pem").sign(digest)
    assert "cannot load the fleet CA" in v.warm()
    for _ in range(2):  # the second record goes through the remembered miss
        assert "cannot load the fleet CA" in v.check("robot1", digest, sig)
    good = RecordVerifier(creds)
    assert good.warm() is None and good.check("robot1", digest, sig) is None


def test_a_cloud_says_at_ready_that_its_ca_does_not_load(creds, tmp_path, caplog):
    import logging
    import shutil

    from scmr_mesh.mesh.data_cloud import CloudData

    bad = tmp_path / "bad"
    shutil.copytree(creds, bad)
    (bad / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n")
    data = CloudData("c1", tmp_path / "ods.sqlite", verifier=RecordVerifier(bad))
    try:
        with caplog.at_level(logging.ERROR, logger="scmr_mesh.mesh.data_cloud"):
            data.after_ready()
            data._checker.submit(lambda: None).result(timeout=30)  # the warm-up ran before this
        assert any("cannot load the fleet CA" in r.getMessage() and "refused" in r.getMessage()
                   for r in caplog.records), caplog.text
    finally:
        data.close()
