"""One job's life on a worker: claim it, fetch its inputs, run it with progress and cancellation
wired to the database, checkpoint its run folder to storage, publish its artifacts.

Independent of the Celery app: `worker.tasks` wraps `JobExecutor.run` in tasks, and tests drive it
directly with test-double runners against real databases and storage.
"""

from __future__ import annotations

import logging
import shutil
import socket
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path, PurePosixPath

from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from service.database import session_scope
from service.job_types import JobType
from service.models import Artifact, Job, JobState, Scene, utcnow
from service.settings import Settings
from service.storage import Storage, job_prefix, run_prefix
from worker.runners import JobCancelled, Runner, RunInputs
from worker.sync import MANIFEST, FolderMirror

log = logging.getLogger(__name__)

RUN_SHARE = 0.95  # progress reported by the runner fills 0..0.95; publishing the rest
DB_WRITE_INTERVAL_S = 1.0


class JobBusy(Exception):
    """Another worker holds a live lease on the job; try again after `retry_in` seconds."""

    def __init__(self, retry_in: float) -> None:
        super().__init__(f"job is running elsewhere; retry in {retry_in:.0f} s")
        self.retry_in = retry_in


@dataclass(frozen=True)
class JobFolder:
    """A job's local folder (WORK/jobs/<job id>), removed when the job ends. Nothing in it is shared
    with another job, so two workers on one work dir never pull or delete each other's inputs.

        runs/<job id>/       the job's run folder, mirrored to storage (`run_prefix`)
        runs/<ancestor id>/  each run it continues, fetched from storage beside it: a run names its
                             parent relative to itself ("../<parent id>"), so the chain resolves
                             under any work dir and a job resumes on any worker
        scene/               a reconstruction's cameras file and videos
        videos/              the rendered MP4s
    """

    root: Path

    def run(self, job_id: str) -> Path:
        return self.root / "runs" / job_id

    @property
    def scene(self) -> Path:
        return self.root / "scene"

    @property
    def videos(self) -> Path:
        return self.root / "videos"


@dataclass(frozen=True)
class Claim:
    job_id: str
    job_type: str  # checked against JobType when the job runs: an unknown one fails the job
    params: dict
    scene_id: str | None
    ancestors: tuple[str, ...]  # parent job first, then its parent, ...: the runs this one continues


class JobExecutor:
    def __init__(
        self,
        settings: Settings,
        sessions: sessionmaker[Session],
        storage: Storage,
        runners: dict[str, Runner],
        device: str = "cpu",
        worker_name: str | None = None,
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.storage = storage
        self.runners = runners
        self.device = device
        self.worker_name = worker_name or socket.gethostname()
        self.work_dir = settings.resolved_work_dir()

    # -- lifecycle ---------------------------------------------------------------------------

    def run(self, job_id: str) -> str | None:
        """Run the job to an end state and return it, or None when there was nothing to do.

        Raises JobBusy (another worker's lease is live) and transient storage / database
        errors after putting the job back to queued, so the caller can retry.
        """
        claim = self.claim(job_id)
        if claim is None:
            return None
        try:
            return self._run_claimed(claim)
        finally:  # storage holds the checkpoints and results; the local copies would only pile up
            shutil.rmtree(self._folder(claim.job_id).root, ignore_errors=True)

    def _folder(self, job_id: str) -> JobFolder:
        return JobFolder(self.work_dir / "jobs" / job_id)

    def _run_claimed(self, claim: Claim) -> str:
        job_id = claim.job_id
        reporter = ProgressReporter(self.sessions, job_id)
        try:
            files = self._execute(claim, reporter)
            self._publish(claim, files, reporter)
        except JobCancelled:
            return self.finish(job_id, JobState.CANCELLED, reporter, stage="cancelled")
        except ValueError as exc:  # fluidcore's bad-input errors name the field: show them as they are
            return self.finish(job_id, JobState.FAILED, reporter, error=str(exc))
        except TRANSIENT_ERRORS:
            self._requeue(job_id, reporter)
            raise
        except SoftTimeLimitExceeded:
            limit = self.settings.job_soft_time_limit
            return self.finish(job_id, JobState.FAILED, reporter, error=f"time limit of {limit} s exceeded")
        except Exception as exc:
            log.exception("job %s failed", job_id)
            return self.finish(job_id, JobState.FAILED, reporter, error=f"{type(exc).__name__}: {exc}")
        return self.finish(job_id, JobState.SUCCEEDED, reporter, stage="done")

    def claim(self, job_id: str) -> Claim | None:
        """Mark the job running on this worker, unless it is finished or another worker's lease is live."""
        with session_scope(self.sessions) as session:
            job = session.scalars(select(Job).where(Job.id == job_id).with_for_update()).first()
            if job is None:
                log.warning("job %s does not exist; dropping its task", job_id)
                return None
            if JobState(job.state).finished:
                return None
            if job.cancel_requested:
                job.state, job.stage, job.finished_at = JobState.CANCELLED, "cancelled", utcnow()
                return None
            now = utcnow()
            lease = timedelta(seconds=self.settings.job_lease_seconds)
            if job.state == JobState.RUNNING and job.heartbeat_at is not None and now - job.heartbeat_at < lease:
                raise JobBusy((job.heartbeat_at + lease - now).total_seconds())
            # Found running with an expired lease: the last attempt died (e.g. hard time limit, OOM kill).
            if job.state == JobState.RUNNING and job.attempts >= self.settings.max_job_attempts:
                job.state, job.finished_at = JobState.FAILED, now
                job.error = f"gave up after {job.attempts} attempts: the worker running it was lost each time"
                return None
            job.state, job.stage, job.error = JobState.RUNNING, "preparing", None
            job.started_at = job.started_at or now
            job.heartbeat_at, job.worker, job.attempts = now, self.worker_name, job.attempts + 1
            log.info("job %s (%s): attempt %d on %s", job.id, job.type, job.attempts, self.worker_name)
            return Claim(job.id, job.type, dict(job.params), job.scene_id, _ancestors(session, job))

    def _execute(self, claim: Claim, reporter: ProgressReporter) -> list[Path]:
        folder = self._folder(claim.job_id)
        mirror = FolderMirror(self.storage, folder.run(claim.job_id), run_prefix(claim.job_id))
        resumed = mirror.pull()
        if resumed:
            log.info("job %s resumes from %d checkpointed files", claim.job_id, len(resumed))
        folder.videos.mkdir(parents=True, exist_ok=True)

        def progress(fraction: float, stage: str) -> None:
            reporter.report(RUN_SHARE * min(max(float(fraction), 0.0), 1.0), stage)
            mirror.push()

        inputs = RunInputs(
            job_id=claim.job_id,
            job_type=claim.job_type,
            params=claim.params,
            run_dir=mirror.folder,
            render_dir=folder.videos,
            device=self.device,
            progress=progress,
            should_cancel=reporter.cancel_requested,
            **self._fetch_inputs(claim, folder),
        )
        files = self.runners[claim.job_type](inputs)
        mirror.push()
        return files

    def _fetch_inputs(self, claim: Claim, folder: JobFolder) -> dict[str, object]:
        """Reconstruct: the scene's cameras file and videos. Others: the parent's run folder, and
        its whole chain of ancestors beside it (rendering follows the chain to the background)."""
        if claim.scene_id is not None:
            return self._fetch_scene(claim.scene_id, folder.scene)
        for job_id in claim.ancestors:
            run = folder.run(job_id)
            FolderMirror(self.storage, run, run_prefix(job_id)).pull()
            if not (run / MANIFEST).is_file():
                raise ValueError(f"job {job_id} has no run folder in storage")
        return {"parent_run": folder.run(claim.ancestors[0])}

    def _fetch_scene(self, scene_id: str, folder: Path) -> dict[str, object]:
        with session_scope(self.sessions) as session:
            scene = session.get(Scene, scene_id)
            if scene is None:
                raise ValueError(f"scene {scene_id} no longer exists")
            cameras_key, video_keys = scene.cameras_key, {c: v["key"] for c, v in scene.videos.items()}
        local = {key: folder / PurePosixPath(key).name for key in [cameras_key, *video_keys.values()]}
        for key, path in local.items():
            self.storage.get_file(key, path)
        return {"cameras_path": local[cameras_key], "videos": {c: local[k] for c, k in video_keys.items()}}

    def _publish(self, claim: Claim, files: list[Path], reporter: ProgressReporter) -> None:
        """Upload the rendered videos and exports and record every artifact (videos, exports,
        manifest, states)."""
        reporter.report(RUN_SHARE, "publish")
        rows = []
        for path in files:
            folder, kind, camera, content_type = _published_as(path)
            key = f"{job_prefix(claim.job_id)}/{folder}/{path.name}"
            self.storage.put_file(key, path, content_type)
            rows.append(
                Artifact(
                    job_id=claim.job_id, name=f"{folder}/{path.name}", kind=kind, camera=camera, key=key,
                    size=path.stat().st_size, content_type=content_type,
                )
            )
        prefix = run_prefix(claim.job_id)
        for info in self.storage.list(f"{prefix}/"):
            name = info.key[len(prefix) + 1 :]
            kind = "manifest" if name == MANIFEST else "state" if name.startswith("states/") else "file"
            content_type = "application/json" if name.endswith(".json") else "application/octet-stream"
            rows.append(
                Artifact(job_id=claim.job_id, name=f"run/{name}", kind=kind, key=info.key, size=info.size,
                         content_type=content_type)
            )
        with session_scope(self.sessions) as session:
            session.execute(delete(Artifact).where(Artifact.job_id == claim.job_id))
            session.add_all(rows)

    # -- end states ----------------------------------------------------------------------------

    def finish(
        self, job_id: str, state: JobState, reporter: ProgressReporter | None = None, stage: str | None = None,
        error: str | None = None,
    ) -> str:
        """Put the job in an end state (also used by the task when transient retries run out)."""
        with session_scope(self.sessions) as session:
            job = session.get(Job, job_id)
            assert job is not None
            job.state, job.error, job.finished_at = state, error, utcnow()
            job.stage = stage or job.stage
            if reporter is not None:
                job.stage_seconds = reporter.final_stage_seconds()
            if state == JobState.SUCCEEDED:
                job.progress = 1.0
        log.info("job %s %s%s", job_id, state.value, f": {error}" if error else "")
        return state.value

    def _requeue(self, job_id: str, reporter: ProgressReporter) -> None:
        """A transient fault: give the job back (no live lease) so the retry can claim it at once."""
        try:
            with session_scope(self.sessions) as session:
                job = session.get(Job, job_id)
                if job is not None and job.state == JobState.RUNNING:
                    job.state, job.stage, job.heartbeat_at = JobState.QUEUED, "waiting to retry", None
                    job.stage_seconds = reporter.final_stage_seconds()
        except Exception:  # the database itself may be what failed; the lease then expires on its own
            log.exception("could not put job %s back in the queue", job_id)


def _ancestors(session: Session, job: Job) -> tuple[str, ...]:
    chain: list[str] = []
    parent_id = job.parent_job_id
    while parent_id is not None:
        chain.append(parent_id)
        parent_id = session.scalar(select(Job.parent_job_id).where(Job.id == parent_id))
    return tuple(chain)


class ProgressReporter:
    """Writes progress, stage, per-stage seconds and the lease heartbeat to the job row.

    Writes are throttled (a runner may report many times a second) except on a stage change.
    """

    def __init__(self, sessions: sessionmaker[Session], job_id: str, stage: str = "preparing") -> None:
        self.sessions, self.job_id = sessions, job_id
        self._stage: str | None = stage
        self._stage_started = time.monotonic()
        self._last_write = 0.0
        with session_scope(sessions) as session:
            job = session.get(Job, job_id)
            self._seconds: dict[str, float] = dict(job.stage_seconds or {}) if job else {}

    def report(self, fraction: float, stage: str) -> None:
        now = time.monotonic()
        stage_changed = stage != self._stage
        self._accumulate(now)
        self._stage = stage
        if not stage_changed and now - self._last_write < DB_WRITE_INTERVAL_S:
            return
        self._last_write = now
        with session_scope(self.sessions) as session:
            job = session.get(Job, self.job_id)
            if job is None:
                return
            job.progress, job.stage, job.heartbeat_at = fraction, stage, utcnow()
            job.stage_seconds = dict(self._seconds)  # the current stage's time so far included

    def cancel_requested(self) -> bool:
        with session_scope(self.sessions) as session:
            return bool(session.scalar(select(Job.cancel_requested).where(Job.id == self.job_id)))

    def final_stage_seconds(self) -> dict[str, float]:
        """Seconds per stage, the current one closed (the job is ending or handing back)."""
        self._accumulate(time.monotonic())
        self._stage = None
        return dict(self._seconds)

    def _accumulate(self, now: float) -> None:
        """Add the time since the last call to the current stage."""
        if self._stage is not None:
            self._seconds[self._stage] = round(self._seconds.get(self._stage, 0.0) + now - self._stage_started, 3)
        self._stage_started = now


def _transient_errors() -> tuple[type[BaseException], ...]:
    from sqlalchemy.exc import OperationalError

    from service.storage import StorageError

    return (StorageError, OperationalError, ConnectionError, TimeoutError)


TRANSIENT_ERRORS = _transient_errors()


def _published_as(path: Path) -> tuple[str, str, str | None, str]:
    """(folder, kind, camera, content type) of a file a runner returned: an MP4 per camera, the
    orbit, a what-if's side-by-side, or an export (fluidcore.exports)."""
    if path.suffix != ".mp4":
        return "exports", "export", None, "application/octet-stream"
    if path.stem in ("orbit", "side_by_side"):
        return "videos", path.stem, None, "video/mp4"
    return "videos", "video", path.stem, "video/mp4"
