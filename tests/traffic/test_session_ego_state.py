"""SumoSession.ego_state reads the ego's subscription: the same values as SUMO's getters at every
step (position, speed, acceleration, leader with the true gap), and None once the ego has left."""

import libsumo
import numpy as np

from vcfusion.records import EGO_ID
from vcfusion.scenario import load_scenario
from vcfusion.traffic.session import LEADER_HORIZON_M, SumoSession


def _getters(session):
    v = libsumo.vehicle
    leader = v.getLeader(EGO_ID, LEADER_HORIZON_M)
    return (v.getLanePosition(EGO_ID), v.getSpeed(EGO_ID), v.getAcceleration(EGO_ID),
            (leader[0], leader[1] + v.getMinGap(EGO_ID)) if leader and leader[0] else None)


def test_ego_state_equals_the_getters_every_step_and_is_none_once_the_ego_left(tmp_path):
    scenario = load_scenario("accident")
    session = SumoSession(scenario, 1, tmp_path / "lc.xml", np.random.default_rng(0))
    try:
        seen_leader = seen_none = 0
        for k in range(4000):
            state = session.ego_state()
            if state is None:
                break
            assert state == _getters(session)
            seen_leader += state[3] is not None
            seen_none += state[3] is None
            # braking, then fast: the leader changes and is lost, and the ego drives off the road's end
            session.set_ego_speed(5.0 if k < 300 else 60.0)
            session.step()
        assert state is None and EGO_ID not in libsumo.vehicle.getIDList()
        assert seen_leader > 100 and seen_none > 100  # both kinds of step were compared
    finally:
        session.close()
