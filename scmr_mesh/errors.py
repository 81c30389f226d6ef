"""The project's error tree.

Every error a user can cause derives from :class:`ScmrError`; the CLI turns it
into one line on stderr and exit status 1.  Messages say what was received and
what to do about it.
"""

from __future__ import annotations


class ScmrError(Exception):
    """Root of every expected scmr-mesh failure (exit status 1 in the CLI)."""


class InputError(ScmrError):
    """A user-supplied input (image, file, argument) is unusable."""


class ImageDecodeError(InputError):
    """Bytes or a file could not be decoded as an image of acceptable size."""


class ConfigError(InputError):
    """A configuration, profile or scenario file is invalid.

    The message names the file, the field and the fix.
    """


class WireError(ScmrError):
    """A message on the wire does not match its schema (bad request or reply)."""


class MeshError(ScmrError):
    """A mesh-level failure: a peer could not start, no tier answered, ..."""


class ScenarioError(ScmrError):
    """A scenario could not be set up or run (not an expectation failure)."""
