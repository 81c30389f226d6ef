"""What one attempt of a request came to, and the reply that won (typed control data of the robot).

A request's record lists its attempts (``{"tier", "node", "outcome", ...}``);
``outcome`` is written as the plain strings below (records, reports and tests
read them), but the robot sets and tests them through :class:`Outcome`, and
an error answer keeps its code after ``error:`` (:func:`error_outcome`).

>>> Outcome.of("error:busy") is Outcome.ERROR, error_outcome("busy") == BUSY
(True, True)
>>> import json; json.dumps({"outcome": Outcome.NO_REPLY})
'{"outcome": "no_reply"}'
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

from scmr_mesh.vocab import Tier

__all__ = ["BUSY", "Outcome", "Reply", "error_outcome"]


class Outcome(str, Enum):
    """The outcome of one attempt (its string is what the record holds)."""

    PENDING = "pending"          # sent, nothing yet
    OK = "ok"                    # a good reply: the winner
    BAD_REPLY = "bad_reply"      # a reply that did not decode or could not be trusted
    MISMATCHED = "mismatched"    # the node's reply is not for this request (robot, seq, frame digest): a replay
    TIMEOUT = "timeout"          # no reply within the deadline
    NO_REPLY = "no_reply"        # the query ended without a reply
    UNREACHABLE = "unreachable"  # no queryable matched: not sent
    SUPERSEDED = "superseded"    # another copy of the same request answered first, or a silent hedge was sent again
    ERROR = "error"              # an error answer (``error:<code>``) or a failed send (``error:send (...)``)

    def __str__(self) -> str:
        return self.value

    @classmethod
    def of(cls, text: str) -> Outcome:
        """The outcome a record's string stands for (``error:...`` is :attr:`ERROR`)."""
        return cls.ERROR if str(text).startswith("error:") else cls(text)


def error_outcome(code: str) -> str:
    """The record's string of an error answer with ``code`` (``error:busy``)."""
    return f"error:{code}"


#: A tier answered busy (the negotiator's admission): try another node, never hedge on it.
BUSY = error_outcome("busy")


@dataclass(frozen=True)
class Reply:
    """The reply that won a request: who served it, its decoded body, its size on the wire."""

    tier: Tier | str
    node: str
    body: dict[str, Any]
    nbytes: int
