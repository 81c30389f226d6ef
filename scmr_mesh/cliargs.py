"""Shared argparse types: every numeric and path flag of every command is checked here.

Base layer (stdlib only).  A bad value gives one line on stderr naming the
flag, the value, what is wrong and a value that works, and exit status 1::

    scmr: error: --rate inf: not a finite number; give a number of frames per second > 0 and <= 10000, e.g. --rate 5

Use the types with ``add_argument(..., type=...)``:

* :class:`Number` (``integer=True`` for counts): finite, within ``[lo, hi]``
  (``lo_open`` for ``> lo``); ``nan``, ``inf`` and out-of-range values are
  refused.  Shorthands: :func:`positive`, :func:`non_negative`, :func:`count`.
* :class:`PathArg`: ``"in-file"``, ``"in-dir"`` and ``"in-path"`` must exist
  and be readable; ``"out-file"`` and ``"out-dir"`` must be creatable: the
  path, or its nearest existing ancestor, is a writable folder (not on a
  read-only file system); an ``out-file`` is not a folder.  ``url=True``
  passes ``scheme://...`` values through (``--ods FILE|URL``).
* :func:`parsed` wraps a project parser (``"23Mb/s"``, ``"5e9"``) so its
  errors and non-finite results are reported the same way.

:class:`ScmrArgumentParser` turns a :class:`BadValue` raised by any of them
into that one line and exit 1 (other usage errors keep argparse's usage text
and exit 2).  ``tests/test_cli_values.py`` walks every command's arguments and
checks each flag against these rules.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any, Callable

__all__ = ["BadValue", "Number", "PathArg", "ScmrArgumentParser", "count", "non_negative", "parsed", "positive"]


class BadValue(argparse.ArgumentTypeError):
    """A flag's value is unusable.

    Attributes
    ----------
    value : str
        What the user gave.
    reason : str
        What is wrong with it.
    fix : str
        What to give instead (may contain ``{flag}``, filled in by the parser).
    """

    def __init__(self, value: str, reason: str, fix: str = "") -> None:
        self.value, self.reason, self.fix = str(value), reason, fix
        super().__init__(f"{reason}" + (f"; {fix}" if fix else ""))

    def line(self, flag: str) -> str:
        """The one-line message for ``flag`` (an option such as ``--rate``, or a positional's name)."""
        fix = self.fix.replace("{flag} ", flag + " " if flag.startswith("-") else "")
        return f"{flag} {shlex.quote(self.value)}: {self.reason}" + (f"; {fix}" if fix else "")


def _fmt(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


class Number:
    """An argparse type for a finite number in a range.

    Parameters
    ----------
    lo, hi : float or int, optional
        Bounds (inclusive unless ``lo_open`` / ``hi_open``).
    integer : bool
        Only whole numbers (``"3"``; ``"3.0"`` and ``"1e3"`` are refused).
    what : str
        What the number is, for the message ("frames per second").
    example : str
        A good value, for the message.
    """

    kind = "number"

    def __init__(self, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
                 hi_open: bool = False, integer: bool = False, what: str = "", example: str | None = None) -> None:
        self.lo, self.hi, self.lo_open, self.hi_open = lo, hi, lo_open, hi_open
        self.integer = integer
        self.what = what
        self.example = example if example is not None else self._default_example()
        self.__name__ = "integer" if integer else "number"  # argparse names the type in its own messages

    def _default_example(self) -> str:
        if self.lo is not None:
            x = self.lo + (1 if self.lo_open else 0)
            if self.hi is not None and x > self.hi:
                x = self.hi
            return _fmt(int(x) if self.integer else float(x))
        return "1" if self.integer else "1.0"

    def describe(self) -> str:
        """``"whole number of frames >= 1 and <= 1000"``."""
        parts = [("a whole number" if self.integer else "a number") + (f" of {self.what}" if self.what else "")]
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {_fmt(self.lo)}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {_fmt(self.hi)}")
        return " ".join(parts[:1]) + ("" if len(parts) == 1 else " " + " and ".join(parts[1:]))

    def _fix(self) -> str:
        return f"give {self.describe()}, e.g. {{flag}} {self.example}"

    def __call__(self, text: str) -> int | float:
        s = str(text).strip()
        try:
            x: int | float = int(s, 10) if self.integer else float(s)
        except ValueError:
            reason = "not a whole number" if self.integer else "not a number"
            raise BadValue(text, reason, self._fix()) from None
        if not math.isfinite(x):
            raise BadValue(text, "not a finite number", self._fix())
        lo_bad = self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo)
        hi_bad = self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi)
        if lo_bad or hi_bad:
            raise BadValue(text, "out of range", self._fix())
        return x

    def bad_values(self) -> list[str]:
        """Values this type must refuse (for the table-driven CLI test)."""
        out = ["nan", "inf", "-inf", "abc"]
        if self.lo is not None:
            out.append(repr(self.lo) if self.lo_open else repr(self.lo - 1))
        if self.hi is not None:
            out.append(repr(self.hi) if self.hi_open else repr(self.hi + 1))
        if self.integer:
            out.append("2.5")
        return out


def positive(what: str = "", *, hi: float | None = None, example: str | None = None, integer: bool = False) -> Number:
    """A finite number > 0 (``integer``: a whole number >= 1)."""
    if integer:
        return Number(lo=1, hi=hi, integer=True, what=what, example=example)
    return Number(lo=0, lo_open=True, hi=hi, what=what, example=example)


def non_negative(what: str = "", *, hi: float | None = None, example: str | None = None,
                 integer: bool = False) -> Number:
    """A finite number >= 0."""
    return Number(lo=0, hi=hi, integer=integer, what=what, example=example)


def count(what: str = "", *, lo: int = 1, hi: int | None = None, example: str | None = None) -> Number:
    """A whole number >= ``lo`` (default 1)."""
    return Number(lo=lo, hi=hi, integer=True, what=what, example=example)


def parsed(parse: Callable[[str], Any], *, what: str, example: str, positive: bool = True,
           keep_text: bool = False) -> Callable[[str], Any]:
    """Wrap a project parser (``"23Mb/s"`` -> bytes/s): its errors and non-finite results become :class:`BadValue`.

    The wrapped parser raises ``ValueError`` or a :class:`~scmr_mesh.errors.ScmrError`
    on bad input; numbers it returns (or the numbers of a list) are checked
    finite, and > 0 with ``positive`` (else >= 0).  ``keep_text`` returns the
    text as given (the command parses it again), else the parsed value.
    """
    from scmr_mesh.errors import ScmrError

    def convert(text: str) -> Any:
        fix = f"give {what}, e.g. {{flag}} {example}"
        try:
            v = parse(text)
        except (ValueError, TypeError, OverflowError, ScmrError) as exc:
            raise BadValue(text, str(exc) or "not understood", fix) from None
        for x in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(x, (int, float)) and not (math.isfinite(x) and (x > 0 if positive else x >= 0)):
                raise BadValue(text, f"not a finite number {'> 0' if positive else '>= 0'}", fix)
        return text if keep_text else v

    convert.kind = "parsed"  # type: ignore[attr-defined]
    convert.bad_values = lambda: ["nan", "inf", "-1", "abc"]  # type: ignore[attr-defined]
    convert.__name__ = "value"
    return convert


# --------------------------------------------------------------------- paths
def _nearest_existing(p: Path) -> Path:
    q = p
    while not q.exists() and q != q.parent:
        q = q.parent
    return q


def _writable_dir(d: Path) -> str | None:
    """None when files can be created in folder ``d``, else why not."""
    if not d.is_dir():
        return f"{d} is a file, not a folder"
    if os.access(d, os.W_OK | os.X_OK):
        # root passes os.access everywhere: try it (/proc, sysfs and full or immutable folders refuse)
        import tempfile

        try:
            os.rmdir(tempfile.mkdtemp(prefix=".scmr-probe-", dir=d))
            return None
        except OSError as exc:
            return f"{d} does not take new files ({exc.strerror or exc})"
    try:
        if os.statvfs(d).f_flag & os.ST_RDONLY:
            return f"{d} is on a read-only file system"
    except OSError:
        pass
    return f"{d} is not writable"


class PathArg:
    """An argparse type for a path that must be usable.

    Parameters
    ----------
    mode : {"in-file", "in-dir", "in-path", "out-file", "out-dir"}
    as_path : bool
        Return a :class:`~pathlib.Path` (default: the string as given).
    url : bool
        Let ``scheme://...`` through unchecked (``FILE|URL`` flags).
    what : str
        What the path is, for the message ("a scenario TOML file").
    example : str
        A good value, for the message.
    """

    kind = "path"
    MODES = ("in-file", "in-dir", "in-path", "out-file", "out-dir")

    def __init__(self, mode: str, *, as_path: bool = False, url: bool = False, what: str = "",
                 example: str = "") -> None:
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        self.mode, self.as_path, self.url = mode, as_path, url
        self.what = what or {"in-file": "an existing readable file", "in-dir": "an existing folder",
                             "in-path": "an existing file or folder", "out-file": "a file path in a writable folder",
                             "out-dir": "a folder that can be created or written"}[mode]
        self.example = example
        self.__name__ = "path"

    def _fix(self) -> str:
        return f"give {self.what}" + (f", e.g. {{flag}} {self.example}" if self.example else "")

    def problem(self, text: str) -> str | None:
        """Why ``text`` is unusable, or None."""
        if not text.strip():
            return "empty path"
        if "\0" in text:
            return "the path holds a NUL byte"
        p = Path(text).expanduser()
        if self.mode.startswith("in-"):
            if not p.exists():
                return "no such file or folder"
            if self.mode == "in-file" and p.is_dir():
                return "a folder, not a file"
            if self.mode == "in-dir" and not p.is_dir():
                return "a file, not a folder"
            if not os.access(p, os.R_OK | (os.X_OK if p.is_dir() else 0)):
                return "not readable"
            return None
        if p.exists():
            if self.mode == "out-file":
                if p.is_dir():
                    return "a folder, not a file"
                return None if os.access(p, os.W_OK) else _writable_dir(p.parent) or "not writable"
            return _writable_dir(p)
        return _writable_dir(_nearest_existing(p.parent if self.mode == "out-file" else p))

    def __call__(self, text: str) -> str | Path:
        text = str(text)
        if self.url and "://" in text:
            return text
        why = self.problem(text)
        if why is not None:
            raise BadValue(text, why, self._fix())
        return Path(text) if self.as_path else text


# -------------------------------------------------------------------- parser
class ScmrArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose value errors are one line and exit 1.

    A :class:`BadValue` raised by a flag's type becomes ``scmr: error: FLAG
    VALUE: reason; fix`` on stderr and exit status 1.  Every other usage error
    (unknown flag, missing argument, bad choice) keeps argparse's usage text
    and exit status 2.  Sub-parsers inherit the class.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # "--rate -inf", "--x -1e3": values, not options (argparse only knows -1 and -1.5)
        self._negative_number_matcher = re.compile(
            r"^-(\d+|\d*\.\d+|\d+\.?\d*[eE][-+]?\d+|inf|infinity|nan)$", re.IGNORECASE)

    def error(self, message: str):  # type: ignore[override]
        exc = sys.exc_info()[1]
        bad = exc.__context__ if isinstance(exc, argparse.ArgumentError) else None
        if isinstance(bad, BadValue):
            flag = exc.argument_name or "argument"
            self.exit(1, f"scmr: error: {bad.line(flag)}\n")
        super().error(message)
