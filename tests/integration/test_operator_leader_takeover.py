"""Two operator replicas with leader election on the real control plane: the leader is
killed (SIGKILL) in the middle of a 100-Vehicle rollout and a Mission start, the standby
takes the Lease and finishes both — the Vehicles and the Missions run on one engine, so
one Lease covers both — and every action is done exactly once: pods, claims and Jobs
made, Vehicle and Mission status transitions, the Mission's fence command sent
(:mod:`tests.support.takeover` says how each is counted). How long the takeover took is a
figure (``python -m bench leader``), not a limit here. About two minutes warm.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from roost_localcluster.cluster import Cluster
from tests.support.takeover import kill_the_leader

# serial: a 100-Vehicle rollout and a kill timed into its middle
pytestmark = [pytest.mark.cluster, pytest.mark.serial]


def test_a_standby_takes_over_a_killed_leader_and_does_nothing_twice(
    roost_crds: Cluster, tmp_path: Path
) -> None:
    result = kill_the_leader(roost_crds, tmp_path, fleet=100)
    assert 0 < result.at_kill.pods < 100, f"killed mid-way through the rollout: {result.at_kill}"
    assert result.at_kill.claims >= 1, "killed once the Mission had started claiming"
    assert result.doubles == []
    assert result.pods == 100, "every vehicle's pod, once"
    assert (result.claims, result.jobs) == (2, 2), "the Mission's claims and Jobs, once"
    assert result.fences == 2, "the Mission's fence sent to each crew vehicle, once"
    assert result.standby_acted == (), "a standby watches, queues and reconciles nothing"
