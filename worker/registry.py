"""The job-type registry: one entry per job type that does real work.

A job type is a name, the queue it runs on, the pydantic model of its parameters, its stages and
one function ``run(ctx, params)``. The gateway accepts a submission only for a registered type,
so an endpoint whose pipeline has not landed answers 409 "not available in this build"
instead of queueing a fake job. Adding
the relight job when the PBR pass lands is one function and one line::

    def run_relight(ctx: JobContext, p: RelightRequest) -> None: ...
    register(JobType("relight", QUEUE_RENDER, RelightRequest, run_relight, stages=("relight",)))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping

from pydantic import BaseModel

if TYPE_CHECKING:
    from worker.jobs import JobContext


@dataclass(frozen=True)
class JobType:
    name: str
    queue: str
    params: type[BaseModel]
    run: Callable[["JobContext", BaseModel], None]
    stages: tuple[str, ...]
    needs_scene: bool = True
    #: Returns why this build cannot serve a valid request (e.g. it asks for a stage that has not
    #: landed), or None; the gateway then answers 409 and queues nothing.
    unavailable: Callable[[BaseModel], str | None] | None = None
    #: ``(session, scene_id, tenant) -> reason or None``: what the scene must have before this job
    #: can run (e.g. a finished reconstruction); the gateway answers 409 with the reason.
    precondition: Callable[[object, str, str], str | None] | None = None
    #: A chained job type (the training stages): ``{stage name: run(ctx, params)}``. Each stage
    #: of a job is then its own RQ job, enqueued behind the previous one with ``depends_on``; the
    #: job's row in the database tracks the chain, and a retry resumes at the first stage that is
    #: not done. ``run`` is unused for such a type.
    stage_fns: Mapping[str, Callable[["JobContext", BaseModel], None]] | None = None
    #: The stages a request asks for (chained types: e.g. the requested subset of the chain, in
    #: chain order); default: all of :attr:`stages`.
    stages_for: Callable[[BaseModel], tuple[str, ...]] | None = None

    @property
    def chained(self) -> bool:
        return self.stage_fns is not None

    def stages_of(self, params: BaseModel) -> tuple[str, ...]:
        return tuple(self.stages_for(params)) if self.stages_for is not None else self.stages


REGISTRY: dict[str, JobType] = {}


def register(jt: JobType) -> JobType:
    if jt.name in REGISTRY and REGISTRY[jt.name] is not jt:
        raise ValueError(f"job type {jt.name!r} is already registered")
    REGISTRY[jt.name] = jt
    return jt


def job_type(name: str) -> JobType | None:
    """The registered job type ``name`` (importing the built-in job types first), or None."""
    import worker.jobs  # noqa: F401  (registers the render type)
    import worker.reconstruct  # noqa: F401  (the chain of stages)
    import worker.relight  # noqa: F401  (relight and night)

    return REGISTRY.get(name)
