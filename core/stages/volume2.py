"""The second volume rendering stage (paper Sec. 3.3: stages (a) and (b) alternate).

The volume stage again (:mod:`core.stages.volume`, Eq. 4 with the supplement's weights), started
from the first volume stage's scene graph and sky, and supervised by the refined G-buffer priors
of :mod:`core.stages.generative_refine` instead of the raw inverse-model priors. Its settings are a
:class:`core.stages.volume.VolumeSettings` with ``init_from_graph=True`` (the profile table in
:mod:`core.stages.chain`); density control is off by default (the geometry is already there).
"""

from __future__ import annotations

from core.stages.volume import run_stage as _run_volume_stage


def run_stage(ctx) -> dict:
    """Run the volume stage for ``volume2`` (the chain gives it the refined priors: the latest
    prior stage before it) and return its summary."""
    return _run_volume_stage(ctx)


__all__ = ["run_stage"]
