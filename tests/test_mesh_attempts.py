"""Typed control data of the robot (issue 21): attempt outcomes and the winning reply."""

from __future__ import annotations

import json

import pytest

from scmr_mesh.mesh.attempts import BUSY, Outcome, Reply, error_outcome
from scmr_mesh.vocab import Tier


def test_outcomes_keep_the_strings_records_hold():
    assert [o.value for o in Outcome] == ["pending", "ok", "bad_reply", "mismatched", "timeout", "no_reply",
                                          "unreachable", "superseded", "error"]
    rec = {"attempts": [{"tier": Tier.CLOUD, "outcome": Outcome.OK}, {"tier": Tier.LEADER, "outcome": BUSY}]}
    assert json.loads(json.dumps(rec)) == {"attempts": [{"tier": "cloud", "outcome": "ok"},
                                                        {"tier": "leader", "outcome": "error:busy"}]}


@pytest.mark.parametrize("text, want", [("ok", Outcome.OK), ("error:busy", Outcome.ERROR),
                                        ("error:send (closed)", Outcome.ERROR), ("timeout", Outcome.TIMEOUT)])
def test_a_record_string_reads_back_as_its_outcome(text, want):
    assert Outcome.of(text) is want


def test_an_unknown_outcome_string_is_refused():
    with pytest.raises(ValueError):
        Outcome.of("maybe")


def test_the_winning_reply_is_a_frozen_value():
    r = Reply(Tier.LOCAL, "r1", {"mask_png": b"x"}, 0)
    assert r == Reply("local", "r1", {"mask_png": b"x"}, 0) and error_outcome("busy") == BUSY
    with pytest.raises(AttributeError):
        r.node = "r2"  # type: ignore[misc]


def test_the_robot_and_the_data_services_are_context_managers(tmp_path):
    """Zenoh resources owned with ``with`` (issue 21): leaving the block closes them."""
    from scmr_mesh.mesh.data_cloud import CloudData
    from scmr_mesh.mesh.robot import Robot

    with Robot("r1", tmp_path / "r1") as r:
        assert not r._records.closed
    assert r._records.closed
    with CloudData("c", tmp_path / "ods.sqlite") as cloud:
        pass
    with pytest.raises(Exception):
        cloud.ods.counts()  # closed with the block
