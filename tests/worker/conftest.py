"""The worker tests share the service fixtures; ``long_zip``, a bundle slow to export, is shared by
the fault and supervision tests."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services"))
from conftest_shared import *  # noqa: E402,F401,F403
from svc_support import make_bundle, zip_bundle  # noqa: E402


@pytest.fixture(scope="module")
def long_zip(tmp_path_factory):
    """A bundle whose export takes several seconds (40 frames of 480x360: ~3 s on a quiet 2-core
    machine; the export reads the captured frames only, so no ground truth is stored)."""
    d = tmp_path_factory.mktemp("long")
    return zip_bundle(make_bundle(d / "b", frames=40, width=480, height=360, test_frames=5, with_gt=False),
                      d / "long.zip")
