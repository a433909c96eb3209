"""Helpers of the worker tests against a real gateway (imported by file name: unique basename)."""

from __future__ import annotations

import httpx

from conftest_shared import OPERATOR_KEY


def api(base: str) -> httpx.Client:
    """An operator's client of the gateway at ``base``."""
    return httpx.Client(base_url=base, headers={"Authorization": f"Bearer {OPERATOR_KEY}"}, timeout=30)


def upload(c, path) -> str:
    """Upload the bundle archive at ``path`` through ``c`` (an httpx or a test client); its scene id."""
    r = c.post("/scenes", content=path.read_bytes(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def job(c, jid) -> dict:
    """The job's ``JobOut`` document."""
    r = c.get(f"/jobs/{jid}")
    assert r.status_code == 200, r.text
    return r.json()
