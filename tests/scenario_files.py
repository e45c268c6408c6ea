"""Shared helpers of the test suite (a plain module: `conftest` names clash across test folders)."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


def write_scenario(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    """A scenario file in tmp_path whose relative paths point at the repo's sumo_net."""
    path = tmp_path / name
    net = (REPO / "sumo_net").as_posix()
    path.write_text(text.replace("NET_DIR", net))
    return path
