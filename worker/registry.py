"""The job-type registry: every job type that does real work, imported explicitly from its module
(one module per type: schema -> core call -> artifacts). The job modules register nothing
themselves; each defines a ``JOB_TYPE`` (:class:`worker.runtime.JobType`) and this list names them.

The gateway accepts a submission only for a registered type, so an endpoint whose pipeline has not
landed answers 409 "not available in this build" instead of queueing a fake job. Adding a job type
is one module ``worker/<type>.py`` with ``run(ctx, params)`` and ``JOB_TYPE = JobType(...)``, and
one entry in :data:`JOB_MODULES`.
"""

from __future__ import annotations

from worker import night, reconstruct, relight, render
from worker.runtime import JobType

#: The job modules, each with its ``JOB_TYPE``.
JOB_MODULES = (render, reconstruct, relight, night)

REGISTRY: dict[str, JobType] = {m.JOB_TYPE.name: m.JOB_TYPE for m in JOB_MODULES}


def job_type(name: str) -> JobType | None:
    """The registered job type ``name``, or None."""
    return REGISTRY.get(name)
