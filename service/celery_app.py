"""The Celery application: configuration and task names only, no tasks and no torch, so the API
sends jobs with it by name. `worker.tasks` registers one task per `JobType` under the same names;
workers start with `-A worker.tasks`.

Production choices, each for a reason:
- acks_late + task_reject_on_worker_lost: a job whose worker dies is redelivered, and the
  run folder's per-frame checkpoints in storage let the next worker resume it;
- prefetch 1 and one `gpu` queue consumed with concurrency 1 per GPU: a worker never holds
  a second long job hostage while running the first;
- soft limit (the job fails cleanly with a message) below the hard limit (the child is killed);
- no result backend: job state lives in the service's own database;
- the broker's visibility timeout outlasts the hard time limit, otherwise Redis would
  hand a still-running job to a second worker. A dead worker's job does not wait for it: the
  job's heartbeat stops, and the API's reaper (service.queue.reap_stale) sends it again once the
  lease (16 s) has passed; the message Redis hands out hours later finds the job finished, or
  running under a newer lease token, and is dropped.
"""

from __future__ import annotations

from celery import Celery

import fluidcore  # noqa: F401  before the tasks import torch: sets OpenMP's wait policy

from service.job_types import JobType
from service.settings import GPU_QUEUE, Settings

TASK_PREFIX = "fluidnexus."


def task_name(job_type: JobType) -> str:
    """The Celery task that runs jobs of this type: the name the API sends and the worker registers."""
    return f"{TASK_PREFIX}{job_type.value}"


def make_celery(settings: Settings) -> Celery:
    app = Celery("fluidnexus", broker=settings.resolved_broker_url())
    transport_options: dict[str, object] = {"visibility_timeout": settings.job_hard_time_limit + 600}
    if settings.broker_key_prefix:
        transport_options["global_keyprefix"] = settings.broker_key_prefix
    if settings.is_embedded_broker():
        folder = settings.broker_folder()
        (folder / "processed").mkdir(parents=True, exist_ok=True)
        transport_options = {
            "data_folder_in": str(folder),
            "data_folder_out": str(folder),
            "processed_folder": str(folder / "processed"),
            "store_processed": False,
            "control_folder": str(folder / "control"),  # kombu's default is ./control, wherever serve runs
        }
    app.conf.update(
        broker_transport_options=transport_options,
        broker_connection_retry_on_startup=True,
        task_default_queue=GPU_QUEUE,
        task_routes={f"{TASK_PREFIX}*": {"queue": GPU_QUEUE}},
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_soft_time_limit=settings.job_soft_time_limit,
        task_time_limit=settings.job_hard_time_limit,
        task_ignore_result=True,
        result_backend=None,
        task_serializer="json",
        accept_content=["json"],
        worker_hijack_root_logger=False,
        # The filesystem transport has no fanout exchange for remote control.
        worker_enable_remote_control=not settings.is_embedded_broker(),
    )
    return app
