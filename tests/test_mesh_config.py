"""Zenoh config layering and validation (no network; < 2 s)."""

from __future__ import annotations

import json

import pytest

from scmr_mesh.errors import ConfigError
from scmr_mesh.mesh.config import DEFAULTS, MeshConfig, build_config


def _get(conf, key):
    return json.loads(conf.get_json(key))


def _norm(v):
    """Numbers as floats (zenoh reports retry periods as 50.0), recursively."""
    if isinstance(v, dict):
        return {k: _norm(x) for k, x in v.items()}
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v


def test_defaults_applied():
    conf = build_config(MeshConfig())
    for key, value in DEFAULTS.items():
        assert _norm(_get(conf, key)) == _norm(value), key
    assert _get(conf, "mode") == "peer"


def test_layers_file_then_cfg_then_flags(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ transport: { link: { tx: { lease: 2000, keep_alive: 5 } } }, scouting: { gossip: { enabled: false } } }')
    conf = build_config(MeshConfig(config_file=str(f)))
    assert _get(conf, "transport/link/tx/lease") == 2000  # file beats defaults
    assert _get(conf, "transport/link/tx/keep_alive") == 5
    assert _get(conf, "scouting/gossip/enabled") is False
    assert _get(conf, "transport/unicast/open_timeout") == 1000  # default where the file is silent
    conf = build_config(MeshConfig(config_file=str(f), cfg=["transport/link/tx/lease:1500"]))
    assert _get(conf, "transport/link/tx/lease") == 1500  # --cfg beats the file
    conf = build_config(MeshConfig(config_file=str(f), cfg=["transport/link/tx/lease:1500"], lease_ms=700,
                                   listen=["tcp/127.0.0.1:1"], connect=["tcp/127.0.0.1:2"], mode="client"))
    assert _get(conf, "transport/link/tx/lease") == 700  # flags beat --cfg
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:1"]
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:2"]
    assert _get(conf, "mode") == "client"


@pytest.mark.parametrize("cfg,needle", [
    (["transport/link/tx/keep_alive:0"], "keep_alive"),
    (["transport/link/tx/keep_alive:1"], "keep_alive"),
    (["transport/link/tx/lease:0"], "lease"),
    (["transport/link/tx/lease:5"], "lease"),
    (["no/such/key:1"], "no/such/key"),
    (["transport/link/tx/lease:'x'"], "lease"),
    (["missing-colon"], "KEY:JSON5"),
])
def test_unusable_settings_rejected(cfg, needle):
    with pytest.raises(ConfigError) as ei:
        build_config(MeshConfig(cfg=cfg))
    assert needle in str(ei.value)


def test_lease_flag_validated():
    with pytest.raises(ConfigError, match="lease"):
        build_config(MeshConfig(lease_ms=0))


def test_missing_or_bad_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        build_config(MeshConfig(config_file=str(tmp_path / "nope.json5")))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ConfigError, match="invalid"):
        build_config(MeshConfig(config_file=str(bad)))


def test_example_peer_configs_load(repo_root):
    files = sorted((repo_root / "peers").glob("*.json5"))
    assert files, "peers/*.json5 examples missing"
    for f in files:
        build_config(MeshConfig(config_file=str(f)))


def test_wait_before_close_follows_the_lease_unless_pinned(tmp_path):
    from scmr_mesh.mesh.config import WAIT_BEFORE_CLOSE_KEY as key

    # half the lease: default 500 ms -> 250 ms; --lease-ms wins over the default (in microseconds)
    assert _get(build_config(MeshConfig()), key) == 250_000
    assert _get(build_config(MeshConfig(lease_ms=150)), key) == 75_000
    # an explicit --cfg or a config file keeps its own value
    assert _get(build_config(MeshConfig(lease_ms=150, cfg=[f"{key}:2000000"])), key) == 2_000_000
    f = tmp_path / "z.json5"
    f.write_text("{ transport: { link: { tx: { queue: { congestion_control: { block: { wait_before_close: 3000000 } } } } } } }")
    assert _get(build_config(MeshConfig(config_file=str(f), lease_ms=150)), key) == 3_000_000


def test_bad_setting_fails_before_the_service_starts(tmp_path):
    """`scmr cloud --lease-ms 0` is refused before workers are forked or a store is created."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "cloud", "--node", "c", "--lease-ms", "0"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1  # the flag is refused by its argparse type (scmr_mesh.cliargs)
    assert r.stderr.startswith("scmr: error: --lease-ms 0: out of range")
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "cloud", "--insecure", "--node", "c", "--cfg", "transport/link/tx/lease:0"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1  # the same setting through --cfg: refused by the config check, still before anything
    assert "lease must be an integer >= 10 ms, got 0" in r.stderr
    assert "workers ready" not in r.stderr and "Traceback" not in r.stderr
    assert list(tmp_path.iterdir()) == []  # no run dir, no operational data store
