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

from celery import Task, bootsteps
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
from service.worker_beats import MainClock, WorkerBeacon, worker_name
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


# The main process's clock, shared with the pool children it forks (made here, at import, in the
# main process: `celery -A worker.tasks` imports this module before it starts the pool).
MAIN_CLOCK = MainClock()
MAIN_TICK_S = settings.job_lease_seconds / 8  # how often the main process ticks
MAIN_SILENT_S = settings.job_lease_seconds / 2  # a child stops beating once the main has not ticked this long


class MainTick(bootsteps.StartStopStep):
    """Ticks `MAIN_CLOCK` from the worker's own timer in the main process (the event loop's
    timer with Redis, Celery's timer thread with the filesystem broker): it stops when the main
    process does, and the children's heartbeats stop with it (service.worker_beats). Worst case
    from a freeze to serve's kill: MAIN_SILENT_S + a beat period + worker_unresponsive_seconds
    + a watch period = 8 + 4 + 60 + 4 = 76 s at the defaults (issue 49: within 90 s)."""

    requires = {"celery.worker.components:Timer"}

    def start(self, worker: object) -> None:
        MAIN_CLOCK.tick()
        self.entry = worker.timer.call_repeatedly(MAIN_TICK_S, MAIN_CLOCK.tick)  # type: ignore[attr-defined]

    def stop(self, worker: object) -> None:
        if getattr(self, "entry", None) is not None:
            self.entry.cancel()


app.steps["worker"].add(MainTick)


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
    """This worker's heartbeat, named after the Celery main process (the pool child's parent),
    beating while that process keeps time."""
    return WorkerBeacon(executor().sessions, worker_name(os.getppid()), settings.job_lease_seconds / 4,
                        alive=lambda: MAIN_CLOCK.age() <= MAIN_SILENT_S)


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
