import os
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"


@pytest.fixture
def accident_path() -> Path:
    return SCENARIOS / "accident.yaml"


def write_scenario(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    """A scenario file in tmp_path whose relative paths point at the repo's sumo_net."""
    path = tmp_path / name
    net = (REPO / "sumo_net").as_posix()
    path.write_text(text.replace("NET_DIR", net))
    return path
