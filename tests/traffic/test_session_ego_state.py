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


def test_session_time_is_sumos_step_start_every_step(tmp_path):
    """SumoSession.time counts SUMO's milliseconds instead of asking getTime() every step: it must
    be round(getTime() - step_s, 9) at every step (the stamp SUMO's outputs use), and its own
    round(.., 6) (the ego table's time)."""
    scenario = load_scenario("accident")
    for step_s in (0.01, 0.003):
        sc = scenario.model_copy(update={"simulation": scenario.simulation.model_copy(update={"step_s": step_s})})
        session = SumoSession(sc, 2, tmp_path / f"lc{step_s}.xml", np.random.default_rng(0))
        try:
            for _ in range(1500):
                session.step()
                assert session.time == round(libsumo.simulation.getTime() - step_s, 9)
                assert round(session.time, 6) == session.time
        finally:
            session.close()


def test_the_counted_step_start_equals_the_rounded_one_for_two_hours_of_steps():
    """The same equality as above by arithmetic alone, over two simulated hours (the longest runs;
    every 37th step start: a stride prime to the step sizes meets every last digit)."""
    for step_ms in (1, 10, 25, 100):
        step_s = step_ms / 1000.0
        for begin_ms in range(0, 7_200_000, 37 * step_ms):
            counted = begin_ms / 1000.0
            assert counted == round((begin_ms + step_ms) / 1000.0 - step_s, 9)
            assert round(counted, 6) == counted
