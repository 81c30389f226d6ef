"""Shared control vocabulary (base layer: no Zenoh, no rerun).

Values are ``str`` enums so that records, reports and wire messages keep
writing the same plain strings (``Tier.CLOUD == "cloud"``, ``json.dumps``
writes ``"cloud"``), while code compares against members instead of string
literals that a typo would silently break.
"""

from __future__ import annotations

from enum import Enum


class Tier(str, Enum):
    """Where a frame was served: the thesis's tiers plus the robot itself.

    >>> Tier("leader") is Tier.LEADER, Tier.CLOUD == "cloud", str(Tier.PEER)
    (True, True, 'peer')
    """

    CLOUD = "cloud"
    LEADER = "leader"
    PEER = "peer"
    LOCAL = "local"

    def __str__(self) -> str:  # f"{tier}" and str(tier) give the plain value, as the records do
        return self.value


#: The tiers served by another node, in the robot's default order of preference.
REMOTE_TIERS: tuple[Tier, ...] = (Tier.CLOUD, Tier.LEADER, Tier.PEER)
