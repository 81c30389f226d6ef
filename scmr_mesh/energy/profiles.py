"""Robot power profiles: the built-in Table 4.3 set plus user TOML files.

A user file looks like ``peers/profiles/example.toml``::

    [profiles.jetson]
    description = "Jetson-class board"
    p_compute_w = 15.0
    p_idle_w = 5.0
    p_up_w = 2.5
    p_down_w = 2.0
    clock_hz = 1.9e9

It is validated against ``schemas/energy-profiles.schema.json``; every problem
raises :class:`~scmr_mesh.errors.ConfigError` naming the file, the field and
the fix.  A user profile with a built-in name replaces the built-in one.
"""

from __future__ import annotations

import json
import logging
from functools import lru_cache
from pathlib import Path
from typing import Any

from scmr_mesh.energy.model import PROFILES, Profile
from scmr_mesh.errors import ConfigError

__all__ = ["SCHEMA_PATH", "load_profiles", "get_profile", "all_profiles"]

log = logging.getLogger(__name__)

#: The JSON schema user profile files must satisfy.
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "schemas" / "energy-profiles.schema.json"

_FIX = {
    "required": "add it (a number; powers in W, clock in Hz)",
    "type": "give a value of the right type (numbers for powers and clocks, a string for description)",
    "exclusiveMinimum": "use a value > 0",
    "minimum": "use a larger value (clocks are in Hz, e.g. 1.5e9 for 1.5 GHz)",
    "maximum": "use a smaller value (powers in W, clocks in Hz)",
    "additionalProperties": "remove or rename it (allowed: description, p_compute_w, p_idle_w, "
    "p_up_w, p_down_w, clock_hz, dvs_levels_hz)",
    "propertyNames": "use a name of lower-case letters, digits, '-' or '_' starting with a letter",
    "minProperties": "define at least one [profiles.NAME] table",
    "minItems": "list at least one clock or drop the field",
    "maxLength": "shorten it",
}


@lru_cache(maxsize=1)
def _schema() -> dict[str, Any]:
    try:
        return json.loads(SCHEMA_PATH.read_text())
    except (OSError, ValueError) as exc:  # pragma: no cover - packaging problem
        raise ConfigError(f"cannot read the profile schema {SCHEMA_PATH}: {exc}") from None


def _field_path(err: Any) -> str:
    parts = [str(p) for p in err.absolute_path]
    if err.validator == "required":
        missing = err.message.split("'")[1] if "'" in err.message else "?"
        parts.append(missing)
    elif err.validator == "additionalProperties":
        extra = err.message.split("'")[1] if "'" in err.message else "?"
        parts.append(extra)
    return ".".join(parts) or "(top level)"


def validate_profiles_doc(doc: Any, *, source: str) -> None:
    """Check a parsed profile document against the schema.

    Raises
    ------
    ConfigError
        Naming ``source`` and, for up to three problems (in path order), the
        offending field and the fix.
    """
    import jsonschema

    validator = jsonschema.Draft202012Validator(_schema())
    errors = sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path])
    if not errors:
        return
    problems = [_describe(e) for e in errors[:3]]
    more = f"; and {len(errors) - 3} more problem(s)" if len(errors) > 3 else ""
    raise ConfigError(f"{source}: " + "; also ".join(problems) + more)


def _describe(err: Any) -> str:
    if "propertyNames" in err.schema_path:
        field, fix = f"profiles.{err.instance}", _FIX["propertyNames"]
    else:
        field = _field_path(err)
        fix = _FIX.get(str(err.validator), "see schemas/energy-profiles.schema.json")
        if len(err.absolute_path) == 0 and err.validator in ("required", "additionalProperties"):
            fix = "put each profile in a [profiles.NAME] table, as in peers/profiles/example.toml"
    return f"field {field}: {err.message}; fix: {fix}"


def load_profiles(path: str | Path) -> dict[str, Profile]:
    """Read and validate a TOML profile file.

    Parameters
    ----------
    path : str or Path
        A TOML file with ``[profiles.NAME]`` tables.

    Returns
    -------
    dict of str to Profile
        The file's profiles by name (built-ins not included).

    Raises
    ------
    ConfigError
        The file is missing, is not TOML, or breaks the schema.
    """
    import tomllib

    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(
            f"{p}: cannot read the profiles file ({exc.strerror}); pass an existing TOML file to --profiles-file"
        ) from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{p}: not valid TOML ({exc}); fix the syntax, see peers/profiles/example.toml") from None
    validate_profiles_doc(doc, source=str(p))
    out: dict[str, Profile] = {}
    for name, d in doc["profiles"].items():
        out[name] = Profile(
            name=name,
            p_compute_w=float(d["p_compute_w"]),
            p_idle_w=float(d["p_idle_w"]),
            p_up_w=float(d["p_up_w"]),
            p_down_w=float(d["p_down_w"]),
            clock_hz=float(d["clock_hz"]),
            description=str(d.get("description", "")),
            dvs_levels_hz=tuple(float(x) for x in d.get("dvs_levels_hz", ())),
            source=str(p),
        )
        if out[name].p_idle_w > out[name].p_compute_w:
            log.warning("%s: profile %s has p_idle_w > p_compute_w; offloading will rarely pay", p, name)
    return out


def all_profiles(*, profiles_file: str | Path | None = None) -> dict[str, Profile]:
    """Built-in Table 4.3 profiles, overlaid with those of ``profiles_file``."""
    merged = dict(PROFILES)
    if profiles_file is not None:
        merged.update(load_profiles(profiles_file))
    return merged


def get_profile(name: str, *, profiles_file: str | Path | None = None) -> Profile:
    """Look a profile up by name.

    Parameters
    ----------
    name : str
        ``leader``, ``robot1`` ... ``robot4`` or a name from ``profiles_file``.
    profiles_file : str or Path, optional
        A user TOML file; its profiles win over built-ins of the same name.

    Raises
    ------
    ConfigError
        Unknown name (the message lists the known ones) or a bad file.

    Examples
    --------
    >>> get_profile("robot2").clock_hz
    2300000000.0
    """
    known = all_profiles(profiles_file=profiles_file)
    if name not in known:
        where = f" or in {profiles_file}" if profiles_file else ""
        raise ConfigError(
            f"unknown energy profile {name!r}; use one of {sorted(known)}"
            f" (built-in{where}), or define it in a file passed as --profiles-file"
        )
    return known[name]
