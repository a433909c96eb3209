"""Shared fixtures: a small valid bundle written without Mitsuba, and a tiny Mitsuba scene."""

from __future__ import annotations

from pathlib import Path

import pytest

from core.bundle.testing import write_fake_bundle

REPO = Path(__file__).resolve().parents[1]


def write_small_bundle(root: Path, *, frames: int = 3, width: int = 32, height: int = 24,
                       with_gt: bool = True) -> Path:
    """A valid bundle of a few frames with simple content (no renderer involved): sky masks,
    LiDAR, a tracked car and a relit set beside the frames."""
    return write_fake_bundle(root, frames=frames, width=width, height=height, with_gt=with_gt, name="small",
                             focal=30.0, source={"kind": "test"}, extras=True)


@pytest.fixture
def one_torch_thread():
    """One torch thread for the test (torch's OpenMP threads spin and steal cores from other
    processes); the previous count restored after."""
    import torch

    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(prev)


@pytest.fixture
def small_bundle(tmp_path) -> Path:
    return write_small_bundle(tmp_path / "small")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A tiny synthetic street rendered by Mitsuba (profile ``tiny``, ~3 s)."""
    from core.synth import generate_scene, profile

    root = tmp_path_factory.mktemp("synth") / "tiny"
    return generate_scene(profile("tiny"), root, progress=False, workers=1)
