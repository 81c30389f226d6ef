"""A fast yes/no check of the wire schemas (private; base layer, pure Python).

:func:`compile_check` turns a JSON Schema (2020-12) that uses only the keywords
the wire messages need into a function ``check(instance) -> bool``, built
from plain closures.  It answers the same as ``jsonschema``'s
``Draft202012Validator(...).is_valid`` (tests/test_wire.py compares them on
generated messages) in a few microseconds instead of about 120, and without
importing jsonschema (about 100 ms, plus 35 ms to compile the five wire
validators: a third of a cloud's start-up).  :mod:`scmr_mesh.wire` uses it
first and asks jsonschema only to explain a message that fails.

Supported: ``type``, ``const``, ``enum``, ``minimum``, ``maximum``,
``exclusiveMinimum``, ``exclusiveMaximum``, ``minLength``, ``maxLength``,
``pattern``, ``minItems``, ``maxItems``, ``items``, ``prefixItems``,
``properties``, ``required``, ``additionalProperties``, ``allOf``, ``anyOf``,
``oneOf``, ``not``, ``if``/``then``/``else``, the wire's ``x-bytes`` and the
annotations (``$schema``, ``$id``, ``title``, ``description``, ``$comment``,
``default``, ``examples``).  Anything else raises :class:`Unsupported`, and
the caller keeps using jsonschema for that schema.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from numbers import Number
from typing import Any, Callable

Check = Callable[[Any], bool]

_ANNOTATIONS = frozenset({"$schema", "$id", "title", "description", "$comment", "default", "examples"})


class Unsupported(ValueError):
    """The schema uses a keyword this checker does not implement."""


# -------------------------------------------------- jsonschema's type rules
def _is_number(x: Any) -> bool:
    t = type(x)
    if t is int or t is float:  # the wire's numbers, without the Number ABC's slow isinstance
        return True
    return t is not bool and isinstance(x, Number)


def _is_integer(x: Any) -> bool:
    if isinstance(x, bool):
        return False
    return isinstance(x, int) or (isinstance(x, float) and x.is_integer())


def _is_finite_number(x: Any) -> bool:
    return _is_number(x) and (not isinstance(x, float) or math.isfinite(x))


def _is_real_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


_TYPES: dict[str, Check] = {
    "string": lambda x: isinstance(x, str),
    "integer": _is_integer,
    "number": _is_number,
    "boolean": lambda x: isinstance(x, bool),
    "null": lambda x: x is None,
    "array": lambda x: isinstance(x, list),
    "object": lambda x: isinstance(x, dict),
}
#: ``strict=True``: a wire peer's numbers, where jsonschema's rules are too lax for
#: untrusted input (an ``integer`` must be a real int, not 1e300; a ``number`` finite).
_STRICT_TYPES: dict[str, Check] = {**_TYPES, "integer": _is_real_int, "number": _is_finite_number}


_TRUE, _FALSE = object(), object()


def _unbool(x: Any) -> Any:
    return _TRUE if x is True else _FALSE if x is False else x


def equal(a: Any, b: Any) -> bool:
    """JSON equality as jsonschema does it: ``1 == 1.0``, but ``True != 1``."""
    if a is b:
        return True
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    if isinstance(a, Sequence) and isinstance(b, Sequence):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    return _unbool(a) == _unbool(b)


# ------------------------------------------------------------------ compile
def compile_check(schema: Any, *, strict: bool = False) -> Check:
    """``check(instance) -> bool`` for ``schema``.

    With ``strict``, ``integer`` accepts only real ints (jsonschema also takes
    ``1e300``) and ``number`` only finite values (jsonschema also takes NaN and
    inf): what :mod:`scmr_mesh.wire` asks of another node's message.

    Raises
    ------
    Unsupported
        A keyword outside the supported list (see the module docstring).
    """
    if schema is True:
        return lambda x: True
    if schema is False:
        return lambda x: False
    if not isinstance(schema, dict):
        raise Unsupported(f"a schema must be an object or a boolean, got {type(schema).__name__}")
    checks: list[Check] = []
    handled = set(_ANNOTATIONS)

    def use(*names: str) -> None:
        handled.update(names)

    if "type" in schema:
        use("type")
        names = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        try:
            tests = [(_STRICT_TYPES if strict else _TYPES)[n] for n in names]
        except (KeyError, TypeError):
            raise Unsupported(f"type {schema['type']!r}") from None
        checks.append(tests[0] if len(tests) == 1 else (lambda x, t=tuple(tests): any(f(x) for f in t)))
    if "const" in schema:
        use("const")
        c = schema["const"]
        # a string is equal only to the same string (equal() compares them with ==)
        checks.append((lambda x, c=c: x == c) if isinstance(c, str) else (lambda x, c=c: equal(x, c)))
    if "enum" in schema:
        use("enum")
        values = list(schema["enum"])
        if values and all(isinstance(e, str) for e in values):  # the common case: a set lookup
            checks.append(lambda x, v=frozenset(values): isinstance(x, str) and x in v)
        else:
            checks.append(lambda x, v=values: any(equal(x, e) for e in v))
    for kw, test in (("minimum", lambda x, b: x >= b), ("maximum", lambda x, b: x <= b),
                     ("exclusiveMinimum", lambda x, b: x > b), ("exclusiveMaximum", lambda x, b: x < b)):
        if kw in schema:
            use(kw)
            checks.append(lambda x, b=schema[kw], t=test: not _is_number(x) or t(x, b))
    if "minLength" in schema:
        use("minLength")
        checks.append(lambda x, n=schema["minLength"]: not isinstance(x, str) or len(x) >= n)
    if "maxLength" in schema:
        use("maxLength")
        checks.append(lambda x, n=schema["maxLength"]: not isinstance(x, str) or len(x) <= n)
    if "pattern" in schema:
        use("pattern")
        rx = re.compile(schema["pattern"])
        checks.append(lambda x, rx=rx: not isinstance(x, str) or rx.search(x) is not None)
    if "minItems" in schema:
        use("minItems")
        checks.append(lambda x, n=schema["minItems"]: not isinstance(x, list) or len(x) >= n)
    if "maxItems" in schema:
        use("maxItems")
        checks.append(lambda x, n=schema["maxItems"]: not isinstance(x, list) or len(x) <= n)
    if "prefixItems" in schema or "items" in schema:
        use("prefixItems", "items")
        prefix = [compile_check(s, strict=strict) for s in schema.get("prefixItems", [])]
        rest = compile_check(schema["items"], strict=strict) if "items" in schema else None

        def items(x, prefix=prefix, rest=rest):
            if not isinstance(x, list):
                return True
            for f, v in zip(prefix, x):
                if not f(v):
                    return False
            return rest is None or all(rest(v) for v in x[len(prefix):])

        checks.append(items)
    if "required" in schema:
        use("required")
        req = tuple(schema["required"])
        def required(x, req=req):
            if isinstance(x, dict):
                for k in req:
                    if k not in x:
                        return False
            return True

        checks.append(required)
    if "properties" in schema or "additionalProperties" in schema:
        use("properties", "additionalProperties")
        props = {k: compile_check(s, strict=strict) for k, s in schema.get("properties", {}).items()}
        extra = compile_check(schema["additionalProperties"], strict=strict) if "additionalProperties" in schema else None

        def properties(x, props=props, extra=extra):
            if not isinstance(x, dict):
                return True
            for k, v in x.items():
                f = props.get(k)
                if f is not None:
                    if not f(v):
                        return False
                elif extra is not None and not extra(v):
                    return False
            return True

        checks.append(properties)
    if "allOf" in schema:
        use("allOf")
        subs = [compile_check(s, strict=strict) for s in schema["allOf"]]
        checks.append(lambda x, subs=subs: all(f(x) for f in subs))
    if "anyOf" in schema:
        use("anyOf")
        subs = [compile_check(s, strict=strict) for s in schema["anyOf"]]
        checks.append(lambda x, subs=subs: any(f(x) for f in subs))
    if "oneOf" in schema:
        use("oneOf")
        subs = [compile_check(s, strict=strict) for s in schema["oneOf"]]
        checks.append(lambda x, subs=subs: sum(1 for f in subs if f(x)) == 1)
    if "not" in schema:
        use("not")
        sub = compile_check(schema["not"], strict=strict)
        checks.append(lambda x, sub=sub: not sub(x))
    if "if" in schema:
        use("if", "then", "else")
        cond = compile_check(schema["if"], strict=strict)
        then = compile_check(schema.get("then", True), strict=strict)
        other = compile_check(schema.get("else", True), strict=strict)
        checks.append(lambda x, c=cond, t=then, e=other: t(x) if c(x) else e(x))
    elif "then" in schema or "else" in schema:
        use("then", "else")  # without "if" they do nothing
    if "x-bytes" in schema:
        use("x-bytes")
        spec = schema["x-bytes"] if isinstance(schema["x-bytes"], dict) else {}
        lo, hi = spec.get("minLength"), spec.get("maxLength")

        def xbytes(x, lo=lo, hi=hi):
            return isinstance(x, (bytes, bytearray)) and (lo is None or len(x) >= lo) and (hi is None or len(x) <= hi)

        checks.append(xbytes)
    unknown = set(schema) - handled
    if unknown:
        raise Unsupported(f"keywords {sorted(unknown)}")
    if not checks:
        return lambda x: True
    if len(checks) == 1:
        return checks[0]

    def every(x, checks=tuple(checks)):  # a loop: a generator in all() costs more than the checks
        for f in checks:
            if not f(x):
                return False
        return True

    return every
