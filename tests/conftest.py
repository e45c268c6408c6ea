import os
import signal
import sys
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
# commonroad-io's generated protobuf modules need protobuf's pure-Python runtime, chosen at protobuf's
# first import, which may be onnx's in this test run (vcfusion.control.commonroad.use_pure_python_protobuf)
os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")
sys.path.insert(0, str(Path(__file__).parent))

# The Ctrl-C tests press Ctrl-C as at a terminal. A suite started as a shell's background job
# (`make test &`, nohup, some CI runners) inherits SIGINT ignored, and so would every process it
# starts: vcfusion then rightly keeps ignoring it, as a background job should, and the tests
# would measure the shell instead of the code. So the test session takes a terminal's SIGINT.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

from scenario_files import SCENARIOS  # noqa: E402


@pytest.fixture
def accident_path() -> Path:
    return SCENARIOS / "accident.yaml"
