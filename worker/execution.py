"""One job's life on a worker: claim it, fetch its inputs, run it with progress and cancellation
wired to the database, checkpoint its run folder to storage, publish its artifacts.

Independent of the Celery app: `worker.tasks` wraps `JobExecutor.run` in tasks, and tests drive it
directly with test-double runners against real databases and storage.
"""

from __future__ import annotations

import logging
import shutil
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy.orm import Session, sessionmaker

from fluidcore.errors import InputError, internal_error
from fluidcore.jobs import Cancelled
from fluidcore.names import safe_join
from service import jobs, leases, scenes
from service.chaining import job_ended
from service.database import session_scope
from service.job_states import Actor
from service.job_types import JobType
from service.leases import Claim, Ended, LeaseLost
from service.models import Artifact, Job, JobState
from service.queue import JobQueue, send_turns
from service.settings import Settings
from service.storage import ObjectNotFound, Storage, StorageError, job_prefix, log_key, run_prefix
from service.bundles import BUNDLE_FOLDER, BUNDLE_TYPE
from service.videos import VIDEO_FOLDER, VIDEO_TYPE, video_kind
from worker.runners import Runner, RunInputs
from fluidcore.runs import MANIFEST, STATES_DIR
from worker.sync import FolderMirror

log = logging.getLogger(__name__)
# Internal errors are logged here, outside the loggers JobLog copies into the job's log: its owner
# reads that log (GET /v1/jobs/{id}/logs), and the exception's text may hold SQL or paths.
incidents = logging.getLogger("fluidnexus.incidents")

RUN_SHARE = 0.95  # progress reported by the runner fills 0..0.95; publishing the rest
DB_WRITE_INTERVAL_S = 1.0
MAX_LOG_BYTES = 1024 * 1024


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


class JobExecutor:
    def __init__(
        self,
        settings: Settings,
        sessions: sessionmaker[Session],
        storage: Storage,
        runners: dict[str, Runner],
        device: str = "cpu",
        worker_name: str | None = None,
        queue: JobQueue | None = None,
    ) -> None:
        """`queue` sends the jobs waiting on a job that succeeded (service.chaining); without one,
        they stay waiting (tests and benchmarks that drive single jobs)."""
        self.queue = queue
        self.settings = settings
        self.sessions = sessions
        self.storage = storage
        self.runners = runners
        self.device = device
        self.worker_name = worker_name or socket.gethostname()
        self.work_dir = settings.resolved_work_dir()

    # -- lifecycle ---------------------------------------------------------------------------

    def run(self, job_id: str) -> str | None:
        """Run the job to an end state and return it (its claim may end it without running it: a
        cancel asked for, the attempts spent), or None when there was nothing to do.

        Raises JobBusy (another worker's lease is live) and transient storage / database
        errors after putting the job back to queued, so the caller can retry.
        """
        claim = self.claim(job_id)
        if claim is None:
            return None
        if isinstance(claim, Ended):
            log.info("job %s %s at its claim", job_id, claim.state.value)
            self._ended(job_id)
            return claim.state.value
        try:
            with JobLog(self.storage, job_id) as job_log:
                log.info("job %s (%s): attempt with lease token %d on %s", job_id, claim.job_type, claim.token,
                         self.worker_name)
                return self._run_claimed(claim, job_log)
        except LeaseLost as lost:  # the folder may be the new runner's too (same machine): leave it
            log.warning("%s; stopped", lost)
            return None
        finally:  # storage holds the checkpoints and results; the local copies would only pile up
            if self._holds(claim):
                shutil.rmtree(self._folder(claim.job_id).root, ignore_errors=True)

    def _holds(self, claim: Claim) -> bool:
        with session_scope(self.sessions) as session:
            return leases.holds(session, claim.job_id, claim.token)

    def _folder(self, job_id: str) -> JobFolder:
        return JobFolder(self.work_dir / "jobs" / job_id)

    def _run_claimed(self, claim: Claim, job_log: JobLog) -> str:
        job_id = claim.job_id
        reporter = ProgressReporter(self.sessions, job_id, claim.token)
        reporter.start_heartbeat(self.settings.job_lease_seconds / 4)
        try:
            files = self._execute(claim, reporter, job_log)
            self._publish(claim, files, reporter)
        except LeaseLost:
            raise
        except Cancelled:
            return self.finish(job_id, JobState.CANCELLED, reporter)
        except InputError as exc:  # what the user can fix names the field: shown as it is
            return self.finish(job_id, JobState.FAILED, reporter, error=str(exc))
        except TRANSIENT_ERRORS:
            self._requeue(job_id, reporter)
            raise
        except SoftTimeLimitExceeded:
            limit = self.settings.job_soft_time_limit
            return self.finish(job_id, JobState.FAILED, reporter, error=f"time limit of {limit} s exceeded")
        except Exception as exc:  # a bug: its text (a stack, SQL, a path) stays in the worker's log
            error = f"{internal_error(incidents, exc, f'job {job_id}')}: see the worker log"
            return self.finish(job_id, JobState.FAILED, reporter, error=error)
        finally:
            reporter.stop_heartbeat()
        return self.finish(job_id, JobState.SUCCEEDED, reporter)

    def claim(self, job_id: str) -> Claim | Ended | None:
        """Mark the job running on this worker, unless it is finished, another worker's lease is
        live, or the claim ends it (`service.leases.claim`)."""
        with session_scope(self.sessions) as session:
            return leases.claim(session, job_id, self.worker_name, self.settings.job_lease_seconds,
                                self.settings.max_job_attempts)

    def _execute(self, claim: Claim, reporter: ProgressReporter, job_log: JobLog) -> list[Path]:
        folder = self._folder(claim.job_id)
        mirror = FolderMirror(self.storage, folder.run(claim.job_id), run_prefix(claim.job_id))
        resumed = mirror.pull()
        if resumed:
            log.info("job %s resumes from %d checkpointed files", claim.job_id, len(resumed))
        folder.videos.mkdir(parents=True, exist_ok=True)

        def progress(fraction: float, stage: str) -> None:
            reporter.report(RUN_SHARE * min(max(float(fraction), 0.0), 1.0), stage)
            if reporter.cancelled:  # honoured at every report, so in stages without frames too
                raise Cancelled(f"cancelled during {stage}")
            reporter.check_held()  # a superseded runner must not push checkpoints
            mirror.push()
            job_log.flush()

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
        if reporter.cancel_requested():  # fetching the inputs can take a while
            raise Cancelled("cancelled while preparing")
        files = self.runners[claim.job_type](inputs)
        reporter.check_held()  # a runner that woke up after its job was queued again pushes nothing
        mirror.push()
        if reporter.cancel_requested():
            raise Cancelled("cancelled before publishing")
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
                raise InputError(f"job {job_id} has no run folder in storage")
        return {"parent_run": folder.run(claim.ancestors[0])}

    def _fetch_scene(self, scene_id: str, folder: Path) -> dict[str, object]:
        with session_scope(self.sessions) as session:
            stored = scenes.files(session, scene_id)
        cameras_key, video_keys = stored.cameras_key, stored.video_keys
        local = {key: safe_join(folder, PurePosixPath(key).name) for key in [cameras_key, *video_keys.values()]}
        for key, path in local.items():
            self.storage.get_file(key, path)
        return {"cameras_path": local[cameras_key], "videos": {c: local[k] for c, k in video_keys.items()}}

    def _publish(self, claim: Claim, files: list[Path], reporter: ProgressReporter) -> None:
        """Upload the rendered videos and exports and record every artifact (videos, exports,
        manifest, states). A render or bundle job publishes its file with its parent's artifacts,
        under the parent's keys (`service.videos`, `service.bundles`), where clients look for it
        and find it the next time."""
        reporter.report(RUN_SHARE, "publish")
        renders = not JobType(claim.job_type).writes_run
        owner = claim.ancestors[0] if renders else claim.job_id
        rows = []
        uploaded: list[str] = []
        try:
            for path in files:
                folder, kind, camera, content_type = _published_as(path)
                key = f"{job_prefix(owner)}/{folder}/{path.name}"
                self.storage.put_file(key, path, content_type)
                uploaded.append(key)
                rows.append(
                    Artifact(
                        job_id=owner, name=f"{folder}/{path.name}", kind=kind, camera=camera, key=key,
                        size=path.stat().st_size, content_type=content_type,
                    )
                )
        except BaseException:  # no half-published set: the retry uploads them all again
            for key in uploaded:
                self.storage.delete(key)
            raise
        if renders:
            with session_scope(self.sessions) as session:
                reporter.owned(session)
                leases.publish_shown(session, owner, rows)
            return
        prefix = run_prefix(claim.job_id)
        for info in self.storage.list(f"{prefix}/"):
            name = info.key[len(prefix) + 1 :]
            kind = "manifest" if name == MANIFEST else "state" if name.startswith(f"{STATES_DIR}/") else "file"
            content_type = "application/json" if name.endswith(".json") else "application/octet-stream"
            rows.append(
                Artifact(job_id=claim.job_id, name=f"run/{name}", kind=kind, key=info.key, size=info.size,
                         content_type=content_type)
            )
        with session_scope(self.sessions) as session:  # still ours: a superseded runner must not publish
            leases.publish_artifacts(session, reporter.owned(session), rows)

    # -- end states ----------------------------------------------------------------------------

    def finish(
        self, job_id: str, state: JobState, reporter: ProgressReporter | None = None, error: str | None = None
    ) -> str:
        """Put the job in an end state (`service.leases.end`), then what follows an end. Without a
        reporter: the task gives up after its transient retries, and a job that ended meanwhile is
        left as it ended."""
        with session_scope(self.sessions) as session:
            if reporter is None:
                job = jobs.get(session, job_id)
                if JobState(job.state).finished:
                    log.info("job %s already %s; not failed again", job_id, job.state)
                    return str(job.state)
                leases.end(job, state, error, None)
            else:
                leases.end(reporter.owned(session), state, error, reporter.final_stage_seconds())
        log.info("job %s %s%s", job_id, state.value, f": {error}" if error else "")
        self._ended(job_id)
        return state.value

    def _ended(self, job_id: str) -> None:
        """What follows every end this worker commits (`service.chaining.job_ended`): the job's
        webhook, its waiting continuations sent or cancelled with theirs; then the owner's next
        job waiting for its turn (`service.queue.send_turns`)."""
        with self.sessions() as session:
            job_ended(session, job_id, self.queue, Actor.WORKER, self.settings)
            if self.queue is not None:
                send_turns(session, job_id, self.queue)

    def _requeue(self, job_id: str, reporter: ProgressReporter) -> None:
        """A transient fault: give the job back (no live lease) so the retry can claim it at once."""
        try:
            with session_scope(self.sessions) as session:
                leases.hand_back(reporter.owned(session), reporter.final_stage_seconds())
        except LeaseLost:  # queued again by the reaper already: the next claim runs it
            log.info("job %s: queued again meanwhile; not handed back", job_id)
        except Exception:  # the database itself may be what failed; the lease then expires on its own
            log.exception("could not put job %s back in the queue", job_id)


class JobLog(logging.Handler):
    """The job's log lines, kept in storage (`log_key`) so the API can show them while it runs.

    Captures INFO and above from the `worker`, `service` and `fluidcore` loggers while the job
    runs (one job per process), appended to the lines of earlier attempts. `flush` uploads the
    whole text when something new arrived; at most MAX_LOG_BYTES are kept (a runaway loop must
    not fill storage), then one line says the rest was dropped."""

    LOGGERS = ("worker", "service", "fluidcore")

    def __init__(self, storage: Storage, job_id: str) -> None:
        super().__init__(logging.INFO)
        self.storage, self.key = storage, log_key(job_id)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        try:
            self.text = storage.read_bytes(self.key).decode(errors="replace")
        except ObjectNotFound:
            self.text = ""
        self._dirty = False
        self._levels: dict[str, int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.text) >= MAX_LOG_BYTES:
            return
        line = self.format(record) + "\n"
        if len(self.text) + len(line) > MAX_LOG_BYTES:
            line = f"... log truncated at {MAX_LOG_BYTES} bytes\n"
        self.text += line
        self._dirty = True

    def __enter__(self) -> JobLog:
        for name in self.LOGGERS:
            logger = logging.getLogger(name)
            self._levels[name] = logger.level
            if logger.level == logging.NOTSET or logger.level > logging.INFO:
                logger.setLevel(logging.INFO)
            logger.addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        for name, level in self._levels.items():
            logging.getLogger(name).removeHandler(self)
            logging.getLogger(name).setLevel(level)
        try:
            self.flush()
        except StorageError:  # the job's outcome is in the database already; only lines are lost
            log.warning("job log %s: could not be stored", self.key, exc_info=True)

    def flush(self) -> None:
        if self._dirty:
            self._dirty = False
            self.storage.put_bytes(self.key, self.text.encode(), "text/plain")


class ProgressReporter:
    """Writes progress (never lower than stored), stage, per-stage seconds and the lease heartbeat
    to the job row.

    Writes are throttled (a runner may report many times a second) except on a stage change.
    """

    def __init__(self, sessions: sessionmaker[Session], job_id: str, token: int, stage: str = "preparing") -> None:
        self.sessions, self.job_id, self.token = sessions, job_id, token
        self._lost = False
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        self._stage: str | None = stage
        self._stage_started = time.monotonic()
        self._last_write = 0.0
        self.cancelled = False  # cancel_requested as of the last write
        with session_scope(sessions) as session:
            self._seconds: dict[str, float] = leases.stage_seconds(session, job_id)

    def report(self, fraction: float, stage: str) -> None:
        now = time.monotonic()
        stage_changed = stage != self._stage
        self._accumulate(now)
        self._stage = stage
        if stage_changed:
            log.info("job %s: stage %s (progress %.0f%%)", self.job_id, stage, 100 * fraction)
        if not stage_changed and now - self._last_write < DB_WRITE_INTERVAL_S:
            return
        self._last_write = now
        with session_scope(self.sessions) as session:
            job = self.owned(session)  # the seconds written include the current stage's so far
            self.cancelled = leases.record_progress(job, fraction, stage, self._seconds)

    def owned(self, session: Session) -> Job:
        """The job row, if this runner still holds its lease token; else LeaseLost (at once,
        without asking the database, once it was found lost)."""
        if self._lost:
            raise LeaseLost(f"job {self.job_id} was claimed by another runner")
        try:
            return leases.held(session, self.job_id, self.token)
        except LeaseLost:
            self._lost = True
            raise

    def check_held(self) -> None:
        """LeaseLost unless this runner still holds the job's lease."""
        with session_scope(self.sessions) as session:
            self.owned(session)

    def start_heartbeat(self, period_s: float) -> None:
        """Refresh `heartbeat_at` every `period_s` from a thread, so a stage that reports no
        progress for a long time (a big prepare, one slow frame) never looks dead."""
        self._heartbeat = threading.Thread(target=self._beat, args=(period_s,), name=f"heartbeat-{self.job_id}", daemon=True)
        self._heartbeat.start()

    def stop_heartbeat(self) -> None:
        self._stop.set()
        if self._heartbeat is not None:
            self._heartbeat.join()

    def _beat(self, period_s: float) -> None:
        while not self._stop.wait(period_s):
            try:
                with session_scope(self.sessions) as session:
                    leases.beat(self.owned(session))
            except LeaseLost:
                return  # the runner finds out at its next report
            except Exception:  # database unreachable: keep trying; the lease decides who runs
                log.warning("job %s: heartbeat failed", self.job_id, exc_info=True)

    def cancel_requested(self) -> bool:
        with session_scope(self.sessions) as session:
            return leases.cancel_requested(session, self.job_id)

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
    """(folder, kind, camera, content type) of a file a runner returned: a video
    (service.videos), a bundle (service.bundles) or an export (fluidcore.exports)."""
    if path.suffix == ".mp4":
        return (VIDEO_FOLDER, *video_kind(path.stem), VIDEO_TYPE)
    if path.suffix == ".zip":
        return BUNDLE_FOLDER, "bundle", None, BUNDLE_TYPE
    return "exports", "export", None, "application/octet-stream"
