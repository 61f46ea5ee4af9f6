"""A job's run as the service reads it back from storage (the worker mirrors it there,
`service.storage.run_prefix`): torch-free, through `fluidcore.runs.RunRecord`."""

from __future__ import annotations

from fluidcore.runs import MANIFEST, RunError, RunRecord
from service.errors import Conflict
from service.storage import ObjectNotFound, Storage, run_prefix


def read_manifest(storage: Storage, job_id: str, label: str | None = None) -> RunRecord:
    """The job's run record as stored (ObjectNotFound, RunError as they come); `label` names the
    run in a RunError (default "job ID's run")."""
    return RunRecord.from_bytes(storage.read_bytes(f"{run_prefix(job_id)}/{MANIFEST}"), label or f"job {job_id}'s run")


def stored_run(storage: Storage, job_id: str) -> RunRecord:
    """The job's run record; Conflict while it has none yet, or an unreadable one."""
    try:
        return read_manifest(storage, job_id)
    except ObjectNotFound:
        raise Conflict(f"job {job_id} has no run in storage yet") from None
    except RunError as exc:
        raise Conflict(str(exc)) from None
