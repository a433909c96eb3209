"""Lint docker/: the compose file runs exactly the commands the tests run, Redis persists, the
workers scale, every BRDF_* variable is a real setting; the Dockerfile pins its base, runs as a
non-root user, uses exec-form commands equal to the compose ones and copies only existing paths."""

from __future__ import annotations

import re

import pytest
import yaml

from services.cli import SERVE_CMD, WORKER_CMD
from svc_support import REPO
from worker.settings import Settings

DOCKER = REPO / "docker"


@pytest.fixture(scope="module")
def compose():
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


@pytest.fixture(scope="module")
def dockerfile():
    text = (DOCKER / "Dockerfile").read_text()
    # join continuation lines, drop comments
    return [ln.strip() for ln in re.sub(r"\\\n", " ", text).splitlines() if ln.strip() and not ln.strip().startswith("#")]


def test_compose_commands_are_the_tested_ones(compose):
    s = compose["services"]
    assert s["gateway"]["command"] == SERVE_CMD
    assert s["worker"]["command"] == WORKER_CMD
    assert set(s) == {"redis", "postgres", "gateway", "worker"}


def test_compose_redis_persists_and_workers_scale(compose):
    s = compose["services"]
    cmd = s["redis"]["command"]
    assert cmd[cmd.index("--appendonly") + 1] == "yes"
    assert any(v.endswith(":/data") for v in s["redis"]["volumes"]) and "redis-data" in compose["volumes"]
    assert str(s["worker"]["deploy"]["replicas"]).startswith("${BRDF_WORKERS")
    assert s["postgres"]["image"].startswith("postgres:15")
    for name in ("gateway", "worker"):
        assert "artifacts:/data" in s[name]["volumes"], f"{name} must share the artifacts volume"
        assert s[name]["depends_on"]["redis"]["condition"] == "service_healthy"
        assert s[name]["build"]["target"] == name and s[name]["build"]["dockerfile"] == "docker/Dockerfile"


def test_compose_environment_names_real_settings(compose):
    fields = set(Settings.model_fields)
    env = compose["services"]["gateway"]["environment"]
    assert env is compose["services"]["worker"]["environment"] or env == compose["services"]["worker"]["environment"]
    for k, v in env.items():
        assert k.startswith("BRDF_") and k[5:].lower() in fields, f"{k} is not a setting"
    assert env["BRDF_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert env["BRDF_REDIS_URL"].startswith("redis://redis:")
    # the URL parses with the settings' own validation
    Settings(database_url=env["BRDF_DATABASE_URL"], redis_url=env["BRDF_REDIS_URL"],
             artifact_store=env["BRDF_ARTIFACT_STORE"])


def _targets(lines):
    out, cur = {}, None
    for ln in lines:
        m = re.match(r"FROM\s+(\S+)(?:\s+AS\s+(\S+))?", ln, re.I)
        if m:
            cur = m.group(2) or m.group(1)
            out[cur] = {"from": m.group(1), "lines": []}
        elif cur:
            out[cur]["lines"].append(ln)
    return out


def test_dockerfile_lint(dockerfile):
    import json

    t = _targets(dockerfile)
    assert set(t) == {"base", "gateway", "worker"}
    base = t["base"]["from"]
    assert ":" in base and not base.endswith(":latest") and re.search(r":\d+\.\d+\.\d+", base), f"unpinned base {base}"
    assert t["gateway"]["from"] == t["worker"]["from"] == "base"
    for target, cmd in (("gateway", SERVE_CMD), ("worker", WORKER_CMD)):
        cmds = [ln for ln in t[target]["lines"] if ln.startswith("CMD ")]
        assert len(cmds) == 1 and json.loads(cmds[0][4:]) == cmd, f"{target}: CMD must be exec form == {cmd}"
    users = [ln for ln in t["base"]["lines"] if ln.startswith("USER ")]
    assert users and users[-1] not in ("USER root", "USER 0"), "the image must not run as root"
    for ln in dockerfile:
        assert not ln.startswith("ADD "), "use COPY, not ADD"
        if ln.startswith("RUN ") and "apt-get install" in ln:
            assert "--no-install-recommends" in ln and "rm -rf /var/lib/apt/lists" in ln
            assert "apt-get update" in ln, "apt-get update and install belong in one RUN"
        if ln.startswith("COPY "):
            for src in ln.split()[1:-1]:
                if not src.startswith("--"):
                    assert (REPO / src).exists(), f"COPY source {src} does not exist"
    assert any(ln.startswith("HEALTHCHECK") and "/healthz" in ln for ln in t["gateway"]["lines"])
    ignore = (DOCKER / "Dockerfile.dockerignore").read_text()
    assert "!core" in ignore and ignore.lstrip().startswith("#") and "\n*\n" in ignore


def test_setup_script_installs_system_packages_guarded():
    text = (REPO / "scripts" / "setup.sh").read_text()
    assert "BRDF_SKIP_SYSTEM_PACKAGES" in text, "the image build must be able to skip chromium"
    assert "command -v apt-get" in text and "id -u" in text
