"""Deployment files: docker-compose.yml validates with `docker-compose config` (the check available
without a Docker daemon) and wires the services the way the settings expect."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def compose() -> dict:
    if shutil.which("docker-compose") is None:
        pytest.skip("docker-compose is not installed (.ci/run installs Debian's package with apt-get)")
    check = subprocess.run(["docker-compose", "-f", "docker-compose.yml", "config", "-q"], cwd=ROOT,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    resolved = subprocess.run(["docker-compose", "-f", "docker-compose.yml", "config"], cwd=ROOT,
                              capture_output=True, text=True, check=True)
    return yaml.safe_load(resolved.stdout)


def test_compose_has_every_service(compose: dict) -> None:
    assert set(compose["services"]) == {"api", "worker", "redis", "postgres", "minio", "minio-init", "flower"}


def test_worker_reserves_a_gpu_and_runs_one_job_at_a_time(compose: dict) -> None:
    worker = compose["services"]["worker"]
    [device] = worker["deploy"]["resources"]["reservations"]["devices"]
    assert device["driver"] == "nvidia" and device["count"] == 1 and "gpu" in device["capabilities"]
    command = worker["command"]
    assert command[command.index("--queues") + 1] == "gpu"
    assert command[command.index("--concurrency") + 1] == "1"


def test_compose_environment_names_real_settings(compose: dict) -> None:
    """A misspelt FLUIDNEXUS_ variable would be silently ignored: each must be a Settings field
    (or fluidcore's models folder variable)."""
    from fluidcore.weights import ENV_VAR as MODELS_VARIABLE

    fields = set(Settings.model_fields)
    for name in ("api", "worker"):
        environment = {k: v for k, v in compose["services"][name]["environment"].items() if k != MODELS_VARIABLE}
        for variable in environment:
            assert variable.startswith("FLUIDNEXUS_"), variable
            assert variable.removeprefix("FLUIDNEXUS_").lower() in fields, variable
        settings = Settings(**{k.removeprefix("FLUIDNEXUS_").lower(): v for k, v in environment.items()})
        assert settings.storage_backend == "s3" and settings.resolved_broker_url().startswith("redis://")
        assert settings.resolved_database_url().startswith("postgresql+psycopg://")


def test_the_bucket_is_created_and_the_api_waits_for_it(compose: dict) -> None:
    services = compose["services"]
    bucket = services["api"]["environment"]["FLUIDNEXUS_S3_BUCKET"]
    assert f"mc mb --ignore-existing local/{bucket}" in " ".join(services["minio-init"]["command"])
    assert services["api"]["depends_on"]["minio-init"]["condition"] == "service_completed_successfully"
