"""Celery tasks, one per `JobType`, registered in a loop under `task_name(job_type)`:
`celery -A worker.tasks worker -Q gpu --concurrency 1`.

Each task only names its job; `JobExecutor` does the work with the runner of the job's type.
Retries are for transient faults only (storage or database unreachable): the run resumes from
its checkpoints, so a retry loses at most the frame in flight. Bad input and bugs fail the job with a message at once.
"""

from __future__ import annotations

import logging
import os
import warnings
from functools import lru_cache

from celery import Task
from celery.exceptions import SecurityWarning
from celery.signals import worker_process_init, worker_process_shutdown

from fluidcore.errors import internal_error
from service.celery_app import make_celery, task_name
from service.database import make_engine, make_sessionmaker
from service.job_types import JobType
from service.leases import JobBusy
from service.models import JobState
from service.queue import CeleryQueue
from service.settings import get_settings
from service.storage import make_storage
from service.worker_beats import WorkerBeacon, worker_name
from worker.execution import TRANSIENT_ERRORS, JobExecutor
from worker.runners import load_runners

log = logging.getLogger(__name__)
settings = get_settings()
app = make_celery(settings)
EMBEDDED = "FLUIDNEXUS_EMBEDDED_WORKER"  # set by `fluidnexus serve` for the worker it starts
if os.environ.get(EMBEDDED) == "1":
    # The embedded worker runs as whoever ran the server (root in a container); Celery's
    # running-as-root warning tells them nothing they did not choose. A standalone worker keeps it.
    warnings.filterwarnings("ignore", category=SecurityWarning)


@worker_process_init.connect
def _init_child(**_: object) -> None:
    """Each prefork child sets its own torch threads, opens its own database connections and
    beats for its worker (service.worker_beats)."""
    executor()
    beacon().start()


@worker_process_shutdown.connect
def _stop_child(**_: object) -> None:
    try:
        beacon().stop()
    except Exception:  # the database may be gone; the row then goes stale within a lease
        log.warning("could not remove this worker's heartbeat", exc_info=True)


@lru_cache(maxsize=1)
def beacon() -> WorkerBeacon:
    """This worker's heartbeat, named after the Celery main process (the pool child's parent)."""
    return WorkerBeacon(executor().sessions, worker_name(os.getppid()), settings.job_lease_seconds / 4)


@lru_cache(maxsize=1)
def executor() -> JobExecutor:
    """This process's executor (created lazily, after the fork, so no connection crosses processes)."""
    device = _configure_torch()
    engine = make_engine(settings.resolved_database_url())
    return JobExecutor(
        settings, make_sessionmaker(engine), make_storage(settings), dict(load_runners(settings.runners)),
        device=device, worker_name=f"{os.uname().nodename}:{os.getpid()}", queue=CeleryQueue(settings),
    )


def _configure_torch() -> str:
    """Threads set deliberately: several processes on one machine must not each take every core."""
    import torch

    threads = settings.worker_torch_threads or (os.cpu_count() or 1)
    torch.set_num_threads(threads)
    device = settings.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    log.info("worker child %d: device %s, %d torch threads", os.getpid(), device, threads)
    return device


def _run(task: Task, job_id: str) -> str | None:
    try:
        with beacon().working():
            return executor().run(job_id)
    except JobBusy as busy:
        raise task.retry(countdown=busy.retry_in, max_retries=None) from None
    except TRANSIENT_ERRORS as exc:
        if task.request.retries >= settings.max_transient_retries:
            error = internal_error(log, exc, f"job {job_id}")  # the fault's text may hold SQL or hosts
            return executor().finish(
                job_id, JobState.FAILED, error=f"gave up after {task.request.retries} retries: {error}: see the worker log"
            )
        countdown = min(300, 10 * 2**task.request.retries)
        log.warning("job %s: transient fault, retry in %d s: %s", job_id, countdown, exc)
        raise task.retry(exc=exc, countdown=countdown) from None


def _register(job_type: JobType) -> Task:
    """The task for one job type; per-type tasks keep the type visible in Flower and routable apart."""

    def run_job(self: Task, job_id: str) -> str | None:
        return _run(self, job_id)

    run_job.__name__ = job_type.value
    run_job.__doc__ = f"Run a {job_type.value} job ({job_type.params.__name__}) and publish what it rendered."
    return app.task(name=task_name(job_type), bind=True)(run_job)


TASKS: dict[JobType, Task] = {job_type: _register(job_type) for job_type in JobType}
