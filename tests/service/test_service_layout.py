"""The service's layout rules: `api` and `worker` share the `service` core and never import each
other, the API process never loads torch, and job types are declared once (`service.job_types
.JobType`) with the request schema, the Celery tasks and the runner check derived from it.

Each check runs in a fresh interpreter, since the test process itself has long imported everything.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from service.celery_app import task_name
from service.job_types import JobType

ROOT = Path(__file__).resolve().parents[2]

IMPORT_ALL = """
import importlib, json, pkgutil, sys
package = importlib.import_module(sys.argv[1])
for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
    importlib.import_module(info.name)
if package.__name__ == "api":
    from api.app import create_app
    create_app().openapi()  # the factory and every route's schema, as `fluidnexus serve` builds them
print(json.dumps(sorted(sys.modules)))
"""

# What each side derives from JobType, as a client and a worker process see it.
DERIVED = """
import json
import service
from api.app import create_app
from service.celery_app import TASK_PREFIX
from service.job_types import JobType
from worker import runners, tasks
schema = create_app().openapi()["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]["application/json"]["schema"]
try:
    runners.load_runners(None)
    runner_error = None
except ValueError as exc:
    runner_error = str(exc)
print(json.dumps({
    "service": service.__file__,
    "job_types": [t.value for t in JobType],
    "schema": sorted(schema["discriminator"]["mapping"]),
    "tasks": sorted(name for name in tasks.app.tasks if name.startswith(TASK_PREFIX)),
    "runner_error": runner_error,
}))
"""


def fresh_python(code: str, tmp_path: Path, *args: str, cwd: Path | None = None) -> object:
    """Run `code` in a new interpreter with its data dir under tmp_path; return its JSON output."""
    env = {**os.environ, "FLUIDNEXUS_DATA_DIR": str(tmp_path / "data")}
    result = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=cwd or tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def loaded_from(modules: list[str], package: str) -> list[str]:
    return [name for name in modules if name == package or name.startswith(f"{package}.")]


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [("api", ("torch", "worker")), ("worker", ("api",)), ("service", ("api", "worker", "torch"))],
)
def test_a_package_never_loads_what_it_must_not(package: str, forbidden: tuple[str, ...], tmp_path: Path) -> None:
    modules = fresh_python(IMPORT_ALL, tmp_path, package)
    assert loaded_from(modules, package), f"{package} was not imported at all"
    assert loaded_from(modules, "service") or package == "service"
    for other in forbidden:
        assert loaded_from(modules, other) == [], f"importing {package} loaded {other}"


def test_job_types_are_the_same_in_schema_tasks_and_runners(tmp_path: Path) -> None:
    derived = fresh_python(DERIVED, tmp_path)
    names = [t.value for t in JobType]
    assert derived["job_types"] == names == ["reconstruct", "predict", "interact", "resimulate", "render", "bundle"]
    # a render is asked for at POST /v1/jobs/{id}/videos/{name}, a bundle at POST /v1/jobs/{id}/bundles,
    # not created like a job that writes a run
    assert derived["schema"] == sorted(t.value for t in JobType if t.writes_run) == sorted(set(names) - {"render", "bundle"})
    assert derived["tasks"] == sorted(task_name(t) for t in JobType)
    assert derived["runner_error"] is None


def test_a_new_job_type_is_one_member_plus_its_runner(tmp_path: Path) -> None:
    """Add one line to JobType (in a copy of `service` that shadows the real one): the API accepts
    the type and the worker registers its task with no other edit, and the worker refuses to start
    until a runner exists for it."""
    overlay = tmp_path / "overlay"
    shutil.copytree(ROOT / "service", overlay / "service", ignore=shutil.ignore_patterns("__pycache__"))
    job_types = overlay / "service" / "job_types.py"
    last = '    RESIMULATE = RunKind.RESIMULATE, ResimulateParams, "parent"\n'
    assert last in job_types.read_text()
    job_types.write_text(job_types.read_text().replace(last, last + '    REPLAY = "replay", ResimulateParams, "parent"\n'))

    derived = fresh_python(DERIVED, tmp_path, cwd=overlay)
    assert Path(derived["service"]).is_relative_to(overlay)
    assert derived["job_types"][4] == "replay"
    assert "replay" in derived["schema"]
    assert "fluidnexus.replay" in derived["tasks"]
    assert "no runner for ['replay']" in derived["runner_error"]
