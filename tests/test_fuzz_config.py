"""Bad scenario, zenoh-config and security-profile files give one clear line, never a traceback.

Hypothesis writes random bytes and mutated copies of shipped files; every failure must be
a :class:`~scmr_mesh.errors.ConfigError`/``ScmrError`` (CLI: exit 1, one ``scmr: error:``
line) naming the file, and for schema problems the field and a fix.  About 4 s.
"""

from __future__ import annotations

import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh.cli import main as scmr
from scmr_mesh.errors import ScmrError

FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture])

toml_scalar = st.one_of(
    st.integers(-10**12, 10**12).map(str), st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.booleans().map(lambda b: str(b).lower()), st.text(max_size=8).map(lambda t: '"' + t.replace("\\", "").replace('"', "") + '"'),
    st.just("[]"), st.just("{}"), st.just('[1, "a"]'),
)


def _one_error_line(err: str, path) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("scmr: error: "), err
    assert "Traceback" not in err
    assert path.name in lines[0], lines[0]
    return lines[0]


@FUZZ
@given(blob=st.binary(max_size=400))
def test_scenario_check_random_bytes(tmp_path_factory, blob, capsys):
    path = tmp_path_factory.mktemp("s") / "scen.toml"
    path.write_bytes(blob)
    rc = scmr(["scenario", "check", str(path)])
    out = capsys.readouterr()
    assert rc == 1
    _one_error_line(out.err, path)


@FUZZ
@given(line=st.integers(0, 200), value=toml_scalar)
def test_scenario_check_mutated_values(tmp_path_factory, repo_root, line, value, capsys):
    src = (repo_root / "peers" / "scenarios" / "cloud-link-drop.toml").read_text().splitlines()
    assign = [i for i, ln in enumerate(src) if re.match(r"^\s*[A-Za-z_]+\s*=\s*[^\[{]", ln)]
    i = assign[line % len(assign)]
    key = src[i].split("=")[0]
    src[i] = f"{key}= {value}"
    path = tmp_path_factory.mktemp("s") / "mut.toml"
    path.write_text("\n".join(src) + "\n")
    rc = scmr(["scenario", "check", str(path)])
    out = capsys.readouterr()
    assert rc in (0, 1), out.err
    if rc == 1:
        msg = _one_error_line(out.err, path)
        assert "field" in msg or "TOML" in msg, msg
        assert "fix" in msg, msg


@FUZZ
@given(blob=st.binary(max_size=300))
def test_zenoh_config_file_random_bytes(tmp_path_factory, blob):
    from scmr_mesh.mesh.config import MeshConfig

    path = tmp_path_factory.mktemp("z") / "z.json5"
    path.write_bytes(blob)
    try:
        MeshConfig(config_file=str(path)).build()
    except ScmrError as exc:
        assert str(path) in str(exc) or path.name in str(exc)


@FUZZ
@given(blob=st.binary(max_size=300))
def test_security_profile_random_bytes(tmp_path_factory, blob):
    from scmr_mesh.security.profile import load_profile

    path = tmp_path_factory.mktemp("p") / "p.toml"
    path.write_bytes(blob)
    with pytest.raises(ScmrError) as info:
        load_profile(path, credentials=None)
    assert str(path) in str(info.value)
