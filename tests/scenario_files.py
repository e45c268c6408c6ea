"""Shared helpers of the test suite (a plain module: `conftest` names clash across test folders)."""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


# b0 departs at 10 m/s 10.4 m ahead of a0 at 30 m/s: within b's spacing, but a0 could not brake in
# time, so SUMO refuses b0 (silently), and holds back c0, which departs after it in that lane
REFUSED_DEPARTURE = """
name: refused
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {max_time_s: 1.0}
metrics: {enabled: false}
prediction: {enabled: false}
vehicles:
  - {name: a, count: 1, lanes: [0], pos_m: [100, 100], speed_mps: 30.0}
  - {name: b, count: 1, lanes: [0], pos_m: [115, 115], speed_mps: 10.0, min_spacing_m: 5.0}
  - {name: c, count: 1, lanes: [0], pos_m: [300, 300], speed_mps: 10.0}
"""


def busy_traffic(max_time_s: float = 120.0) -> str:
    """Poisson cars with spread desired speeds on the 3-lane highway: tens of overtakes in a minute."""
    return f"""
name: busy
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {{step_s: 0.1, max_time_s: {max_time_s:g}}}
metrics: {{enabled: false}}
prediction: {{enabled: false}}
vehicles:
  - {{name: cars, count: 30, vtype: car_mixed, lanes: [0, 1, 2], pos_m: [10, 1500], speed_mps: 20, min_spacing_m: 40}}
flows:
  - {{vtype: car_mixed, vehs_per_hour: 2400, lanes: [0, 1, 2], speed_mps: 25}}
"""


def write_scenario(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    """A scenario file in tmp_path whose relative paths point at the repo's sumo_net."""
    path = tmp_path / name
    net = (REPO / "sumo_net").as_posix()
    path.write_text(text.replace("NET_DIR", net))
    return path


def lifted_highway(tmp_path: Path, z_m: float = 5.0) -> Path:
    """The shipped straight highway with every lane shape point at height z_m (a network with
    elevation, as netconvert writes one), as tmp_path/hill.net.xml."""
    xml = (REPO / "sumo_net" / "highway.net.xml").read_text()
    lifted = re.sub(r'shape="([^"]*)"', lambda m: 'shape="' + " ".join(f"{p},{z_m:.2f}" for p in m.group(1).split()) + '"', xml)
    path = tmp_path / "hill.net.xml"
    path.write_text(lifted)
    return path


# 20 cars on the highway, no ego: a run of about a second of wall time per 100 s simulated
TINY = """
name: tiny
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.1, max_time_s: MAX_TIME}
vehicles:
  - {name: cars, count: 20, lanes: [0, 1, 2], pos_m: [10, 1200], speed_mps: 15, min_spacing_m: 40}
"""


def tiny_scenario(tmp_path: Path, max_time_s: float = 100, extra: str = "") -> Path:
    """The TINY scenario (with `extra` YAML appended) as tmp_path/tiny.yaml."""
    return write_scenario(tmp_path, TINY.replace("MAX_TIME", str(max_time_s)) + extra, "tiny.yaml")
