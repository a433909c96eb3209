"""Pydantic models shared by the gateway, the workers and clients (pydantic only).

Versioned: the current version is :mod:`api_schemas.v1` (``API_VERSION``), re-exported here. A
breaking change makes ``v2`` beside it; job payloads stored in the database carry
``schema_version`` so a worker can refuse a payload it does not understand.
"""

from api_schemas.v1 import *  # noqa: F401,F403
from api_schemas.v1 import __all__ as _v1_all

API_VERSION = "1"
__all__ = ["API_VERSION", *_v1_all]
