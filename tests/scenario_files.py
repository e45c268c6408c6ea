"""Shared helpers of the test suite (a plain module: `conftest` names clash across test folders)."""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


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
