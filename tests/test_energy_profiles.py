"""Profiles: Table 4.3 built-ins and user TOML validated against the schema."""

from __future__ import annotations

import json

import jsonschema
import pytest

from scmr_mesh.energy import PROFILES, get_profile, load_profiles
from scmr_mesh.energy.profiles import SCHEMA_PATH
from scmr_mesh.errors import ConfigError

GOOD = """
[profiles.sbc]
description = "test board"
p_compute_w = 6.0
p_idle_w = 2.5
p_up_w = 1.8
p_down_w = 1.5
clock_hz = 1.5e9
dvs_levels_hz = [0.6e9, 1.5e9]

[profiles.robot1]
p_compute_w = 50
p_idle_w = 20
p_up_w = 80
p_down_w = 100
clock_hz = 1.2e9
"""


def _write(tmp_path, text, name="p.toml"):
    f = tmp_path / name
    f.write_text(text)
    return f


def test_table_4_3_values():
    r2 = PROFILES["robot2"]
    assert (r2.p_compute_w, r2.p_idle_w, r2.p_up_w, r2.p_down_w, r2.clock_hz) == (83, 37, 147.53, 183.80, 2.3e9)
    assert PROFILES["leader"].clock_hz == 3.5e9 and PROFILES["robot4"].clock_hz == 2.83e9
    assert sorted(PROFILES) == ["leader", "robot1", "robot2", "robot3", "robot4"]


def test_schema_is_valid_and_accepts_shipped_example(repo_root):
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    profs = load_profiles(repo_root / "peers" / "profiles" / "example.toml")
    assert profs and all(p.source.endswith("example.toml") for p in profs.values())


def test_user_file_adds_and_overrides(tmp_path):
    f = _write(tmp_path, GOOD)
    sbc = get_profile("sbc", profiles_file=f)
    assert sbc.clock_hz == 1.5e9 and sbc.dvs_levels() == (0.6e9, 1.5e9)
    assert get_profile("robot1", profiles_file=f).clock_hz == 1.2e9  # user wins
    assert get_profile("robot1").clock_hz == 1.0e9  # built-in untouched
    assert get_profile("leader", profiles_file=f) == PROFILES["leader"]


def test_unknown_profile_lists_known_names(tmp_path):
    with pytest.raises(ConfigError, match=r"'nope'.*robot1"):
        get_profile("nope")


@pytest.mark.parametrize(
    "text, field, fix",
    [
        (GOOD.replace("p_idle_w = 2.5\n", ""), "profiles.sbc.p_idle_w", "add it"),
        (GOOD.replace("p_up_w = 1.8", "p_up_w = -1.8"), "profiles.sbc.p_up_w", "> 0"),
        (GOOD.replace("p_up_w = 1.8", 'p_up_w = "fast"'), "profiles.sbc.p_up_w", "right type"),
        (GOOD.replace("clock_hz = 1.5e9", "clock_hz = 1.5"), "profiles.sbc.clock_hz", "Hz"),
        (GOOD.replace('description = "test board"', "p_cpu_w = 3"), "profiles.sbc.p_cpu_w", "remove or rename"),
        (GOOD.replace("[profiles.sbc]", '[profiles."Bad Name"]'), "profiles.Bad Name", "lower-case"),
        ("[robots.x]\np_compute_w = 1\n", "robots", "[profiles.NAME]"),
        ("", "profiles", "[profiles.NAME]"),
    ],
)
def test_bad_profile_file_names_file_field_and_fix(tmp_path, text, field, fix):
    f = _write(tmp_path, text, "bad-profiles.toml")
    with pytest.raises(ConfigError) as exc:
        load_profiles(f)
    msg = str(exc.value)
    assert str(f) in msg and f"field {field}" in msg and "fix:" in msg and fix in msg


def test_toml_syntax_error_and_missing_file(tmp_path):
    f = _write(tmp_path, "[profiles.x\np_compute_w = ", "broken.toml")
    with pytest.raises(ConfigError, match=r"broken\.toml: not valid TOML"):
        load_profiles(f)
    with pytest.raises(ConfigError, match=r"missing\.toml: cannot read"):
        get_profile("x", profiles_file=tmp_path / "missing.toml")
