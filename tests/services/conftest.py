"""The service tests' fixtures live in conftest_shared.py (shared with tests/worker)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest_shared import *  # noqa: E402,F401,F403
