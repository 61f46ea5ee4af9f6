"""Celery tasks, one per job type: `celery -A worker.tasks worker -Q gpu --concurrency 1`.

Each task only names its job; `JobExecutor` does the work. Retries are for transient faults
only (storage or database unreachable): the run resumes from its checkpoints, so a retry
loses at most the frame in flight. Bad input and bugs fail the job with a message at once.
"""

from __future__ import annotations

import logging
import os
from functools import lru_cache

from celery import Task
from celery.signals import worker_process_init

from api.database import make_engine, make_sessionmaker
from api.models import JobState
from api.settings import get_settings
from api.storage import make_storage
from worker.celery_app import TASK_PREFIX, make_celery
from worker.execution import TRANSIENT_ERRORS, JobBusy, JobExecutor
from worker.runners import load_runners

log = logging.getLogger(__name__)
settings = get_settings()
app = make_celery(settings)


@worker_process_init.connect
def _init_child(**_: object) -> None:
    """Each prefork child sets its own torch threads and opens its own database connections."""
    executor()


@lru_cache(maxsize=1)
def executor() -> JobExecutor:
    """This process's executor (created lazily, after the fork, so no connection crosses processes)."""
    device = _configure_torch()
    engine = make_engine(settings.resolved_database_url())
    return JobExecutor(
        settings, make_sessionmaker(engine), make_storage(settings), dict(load_runners(settings.runners)),
        device=device, worker_name=f"{os.uname().nodename}:{os.getpid()}",
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
        return executor().run(job_id)
    except JobBusy as busy:
        raise task.retry(countdown=busy.retry_in, max_retries=None) from None
    except TRANSIENT_ERRORS as exc:
        if task.request.retries >= settings.max_transient_retries:
            return executor().finish(
                job_id, JobState.FAILED, error=f"gave up after {task.request.retries} retries: {exc}"
            )
        countdown = min(300, 10 * 2**task.request.retries)
        log.warning("job %s: transient fault, retry in %d s: %s", job_id, countdown, exc)
        raise task.retry(exc=exc, countdown=countdown) from None


@app.task(name=f"{TASK_PREFIX}reconstruct", bind=True)
def reconstruct(self: Task, job_id: str) -> str | None:
    """Fit particles to a scene's videos (fluidcore.reconstruct.job.run_reconstruct), then render."""
    return _run(self, job_id)


@app.task(name=f"{TASK_PREFIX}predict", bind=True)
def predict(self: Task, job_id: str) -> str | None:
    """Continue a reconstruction into new frames (fluidcore.predict.job.run_predict), then render."""
    return _run(self, job_id)


@app.task(name=f"{TASK_PREFIX}interact", bind=True)
def interact(self: Task, job_id: str) -> str | None:
    """Continue a reconstruction under wind and/or a ball (fluidcore.predict.job.run_interact), then render."""
    return _run(self, job_id)


@app.task(name=f"{TASK_PREFIX}resimulate", bind=True)
def resimulate(self: Task, job_id: str) -> str | None:
    """Re-simulate a reconstruction (fluidcore.predict.job.run_resimulate), then render."""
    return _run(self, job_id)
