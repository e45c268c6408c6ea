"""Small CommonRoad 2020a scenario files written by hand in the published XML layout (for the
reader's tests): a straight road of two lanelets side by side, heading south-east like the
US-101 scenarios, and dynamic obstacles given by their centre in the road's own (s, d) frame."""

from __future__ import annotations

import numpy as np

HEADING = -0.7  # rad, the road's direction (x east, y north)
LANE_W = 3.5
LENGTH = 300.0
ORIGIN = np.array([-40.0, 50.0])
U = np.array([np.cos(HEADING), np.sin(HEADING)])  # along the road
LEFT = np.array([-U[1], U[0]])  # to its left


def world(s: float, d: float) -> np.ndarray:
    """The point s along the road and d left of its right edge (two lanes: d in [0, 7])."""
    return ORIGIN + s * U + d * LEFT


def _point(p) -> str:
    return f"<point><x>{p[0]:.4f}</x><y>{p[1]:.4f}</y></point>"


def _bound(d: float) -> str:
    return "".join(_point(world(s, d)) for s in np.linspace(0.0, LENGTH, 7))


def lanelets_xml() -> str:
    """Lanelet 1 (right lane, d 0-3.5) and 2 (left lane, d 3.5-7), same direction, adjacent."""
    return (f'<lanelet id="1"><leftBound>{_bound(LANE_W)}</leftBound><rightBound>{_bound(0.0)}</rightBound>'
            '<adjacentLeft ref="2" drivingDir="same"/><laneletType>highway</laneletType></lanelet>'
            f'<lanelet id="2"><leftBound>{_bound(2 * LANE_W)}</leftBound><rightBound>{_bound(LANE_W)}</rightBound>'
            '<adjacentRight ref="1" drivingDir="same"/><laneletType>highway</laneletType></lanelet>')


def _state(tag: str, step: int, p, speed: float | None, orientation: float) -> str:
    v = f"<velocity><exact>{speed:.4f}</exact></velocity>" if speed is not None else ""
    return (f"<{tag}><position>{_point(p)}</position><orientation><exact>{orientation:.5f}</exact></orientation>"
            f"<time><exact>{step}</exact></time>{v}<acceleration><exact>0</exact></acceleration></{tag}>")


def obstacle_xml(oid: int, first_step: int, s0: float, speed: float, d_of_t, n_steps: int, length: float = 4.5,
                 width: float = 1.8, kind: str = "car", with_speed: bool = True) -> str:
    """A car driving at `speed` from s0, its lateral position d_of_t(t) (t in s since its first step)."""
    states = []
    for k in range(n_steps):
        t = k * 0.1
        p = world(s0 + speed * t, d_of_t(t))
        tag = "initialState" if k == 0 else "state"
        states.append(_state(tag, first_step + k, p, speed if with_speed else None, HEADING))
    trajectory = "".join(states[1:])
    return (f'<dynamicObstacle id="{oid}"><type>{kind}</type><shape><rectangle><length>{length}</length>'
            f'<width>{width}</width></rectangle></shape>{states[0]}<trajectory>{trajectory}</trajectory>'
            "</dynamicObstacle>")


def planning_problem_xml(pid: int, s: float) -> str:
    p = world(s, LANE_W / 2)
    return (f'<planningProblem id="{pid}"><initialState><position>{_point(p)}</position>'
            f"<velocity><exact>20</exact></velocity><orientation><exact>{HEADING}</exact></orientation>"
            "<yawRate><exact>0</exact></yawRate><slipAngle><exact>0</exact></slipAngle>"
            "<time><exact>0</exact></time></initialState>"
            f'<goalState><time><intervalStart>10</intervalStart><intervalEnd>50</intervalEnd></time></goalState>'
            "</planningProblem>")


def scenario_xml(benchmark_id: str, obstacles: list[str], planning_problem: int = 100) -> str:
    return ('<?xml version="1.0" ?>\n'
            f'<commonRoad affiliation="test" author="test" benchmarkID="{benchmark_id}" commonRoadVersion="2020a" '
            f'date="2020-01-01" source="hand-written" timeStepSize="0.1">'
            "<location><geoNameId>-999</geoNameId><gpsLatitude>999</gpsLatitude><gpsLongitude>999</gpsLongitude>"
            "</location><scenarioTags><highway/></scenarioTags>"
            f"{lanelets_xml()}{''.join(obstacles)}{planning_problem_xml(planning_problem, 10.0)}</commonRoad>\n")


def cosine(t, t0, t1, a, b):
    u = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return a + (b - a) * (1 - np.cos(np.pi * u)) / 2
