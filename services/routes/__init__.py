"""The gateway's routers: :mod:`.system` (health, readiness, metrics, keys), :mod:`.scenes`,
:mod:`.jobs` (submission, status, cancel, retry, artifacts) and :mod:`.envmaps`; each module's
``build(ctx)`` returns its ``APIRouter``. Shared helpers are in :mod:`.common`."""
