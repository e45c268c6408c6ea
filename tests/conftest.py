import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
sys.path.insert(0, str(Path(__file__).parent))

from scenario_files import SCENARIOS  # noqa: E402


@pytest.fixture
def accident_path() -> Path:
    return SCENARIOS / "accident.yaml"
