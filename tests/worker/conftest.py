"""The worker tests share the service fixtures."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services"))
from conftest_shared import *  # noqa: E402,F401,F403
