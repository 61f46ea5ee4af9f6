"""Database tables (SQLAlchemy 2). The Alembic migrations in `migrations/versions` create them;
a change here needs a new migration (`alembic revision --autogenerate`)."""

from __future__ import annotations

import enum
import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Index, Integer, String, Text, UniqueConstraint, text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return uuid.uuid4().hex


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC timestamps on every backend (SQLite hands back naive values)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetime given to a UTC column")
        return value.astimezone(UTC) if value is not None else None

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def finished(self) -> bool:
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


class Base(DeclarativeBase):
    pass


class ApiKey(Base):
    """An API key: only a salted SHA-256 of its secret is stored; `id` is the public half of the key."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    salt: Mapped[str] = mapped_column(String(64))
    secret_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


class Scene(Base):
    """An uploaded capture: a cameras file and one video per camera, all in object storage."""

    __tablename__ = "scenes"
    __table_args__ = (
        Index("ix_scenes_owner_created", "owner", "created_at"),
        UniqueConstraint("owner", "idempotency_key", name="uq_scenes_owner_idempotency_key"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    owner: Mapped[str] = mapped_column(String(128))
    name: Mapped[str] = mapped_column(String(256), default="")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    cameras_key: Mapped[str] = mapped_column(String(512))
    cameras: Mapped[list[str]] = mapped_column(JSON)
    # camera name -> {"key", "filename", "width", "height", "fps", "n_frames", "codec"}
    videos: Mapped[dict[str, dict[str, Any]]] = mapped_column(JSON)
    n_frames: Mapped[int] = mapped_column(Integer)
    fps: Mapped[float] = mapped_column(Float)
    # A retried upload with the same key returns this scene; the hash tells a different upload apart.
    idempotency_key: Mapped[str | None] = mapped_column(String(256), default=None)
    request_hash: Mapped[str | None] = mapped_column(String(64), default=None)


# Job.task_id of a queued job that has no broker task (service.job_states): SENDING while it is
# handed to the broker, UNSENT when the broker did not take it, HELD while it waits its owner's
# turn (service.queue.send)
SENDING = "sending"
UNSENT = "unsent"
HELD = "held"


# The render and bundle jobs still making their file: at most one per file of a job (issue 49: ten
# identical bundle requests at once started six jobs). Their `request_hash` is the hash of the
# file's artifact name (service.jobs.file_hash), so the database refuses a second one.
FILE_IN_THE_MAKING = "type IN ('render', 'bundle') AND state IN ('queued', 'running')"


class Job(Base):
    """One reconstruct / predict / interact / resimulate run and everything the API reports about it."""

    __tablename__ = "jobs"
    __table_args__ = (
        UniqueConstraint("owner", "idempotency_key", name="uq_jobs_owner_idempotency_key"),
        Index("ix_jobs_owner_created", "owner", "created_at"),
        Index("uq_jobs_file_in_the_making", "parent_job_id", "request_hash", unique=True,
              sqlite_where=text(FILE_IN_THE_MAKING), postgresql_where=text(FILE_IN_THE_MAKING)),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    owner: Mapped[str] = mapped_column(String(128))
    type: Mapped[str] = mapped_column(String(32))  # a service.job_types.JobType value
    scene_id: Mapped[str | None] = mapped_column(ForeignKey("scenes.id"), index=True, default=None)
    parent_job_id: Mapped[str | None] = mapped_column(ForeignKey("jobs.id"), index=True, default=None)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)

    state: Mapped[str] = mapped_column(String(16), default=JobState.QUEUED, index=True)
    stage: Mapped[str] = mapped_column(String(64), default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    # stage name -> seconds spent in it (the last stage's time is added when the job ends)
    stage_seconds: Mapped[dict[str, float]] = mapped_column(JSON, default=dict)

    idempotency_key: Mapped[str | None] = mapped_column(String(256), default=None)
    request_hash: Mapped[str | None] = mapped_column(String(64), default=None)
    task_id: Mapped[str | None] = mapped_column(String(64), default=None)  # the broker's task id, SENDING, UNSENT or HELD; NULL: waiting for its parent
    worker: Mapped[str | None] = mapped_column(String(256), default=None)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    # Fencing token: raised by every claim; a runner writes to the job only while it still holds
    # the token it claimed with, so a runner whose lease was taken over stops instead of racing.
    lease_token: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    webhook_url: Mapped[str | None] = mapped_column(String(2048), default=None)  # service.webhooks
    # Bytes the job may write, counted against its owner's stored bytes while it is unfinished
    # (service.quotas): a bundle's declared size, so bundles asked at once cannot each fit the quota.
    reserved_bytes: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")

    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)
    # When this queued job's last hand-off to the broker began (service.queue.take_for_sending), or
    # the reaper last sent it again because its broker message looked lost (reap_stale); it waits a
    # lease before sending it once more, and a hand-off still `SENDING` a lease later is sent again.
    resent_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)


class WorkerBeat(Base):
    """One live Celery worker (service.worker_beats): /readyz needs a recent heartbeat, and the
    reaper reads `idle_since` to tell a lost broker message from a busy worker."""

    __tablename__ = "worker_beats"

    name: Mapped[str] = mapped_column(String(256), primary_key=True)  # host:pid of the Celery main process
    heartbeat_at: Mapped[datetime] = mapped_column(UTCDateTime())
    idle_since: Mapped[datetime | None] = mapped_column(UTCDateTime(), default=None)  # None while it runs a job


# What an artifact is, in the order a job lists them (service.jobs.artifacts): what a user watches
# first, then the downloads for other tools (a sequence as one zip before its single files), then
# what a continuation reads. api.schemas derives the listing's schema from it.
ARTIFACT_KINDS = ("video", "orbit", "side_by_side", "bundle", "export", "state", "manifest", "file")


class Artifact(Base):
    """A downloadable result of a job: an MP4 per camera, the orbit video, bundles, exports,
    particle states, the manifest."""

    __tablename__ = "artifacts"
    __table_args__ = (UniqueConstraint("job_id", "name", name="uq_artifacts_job_name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(512))
    kind: Mapped[str] = mapped_column(String(16))  # one of ARTIFACT_KINDS
    camera: Mapped[str | None] = mapped_column(String(128), default=None)
    key: Mapped[str] = mapped_column(String(1024))
    size: Mapped[int] = mapped_column(BigInteger)
    content_type: Mapped[str] = mapped_column(String(128))
