"""Service settings, read from `FLUIDNEXUS_*` environment variables (and `.env`).

Everything has an embedded default rooted in `data_dir` (FLUIDNEXUS_DATA_DIR, default the per-user
~/.local/share/fluidnexus): SQLite database, local storage
folder and a kombu filesystem broker. Pointing `database_url`, `broker_url` or
`storage_backend` elsewhere switches that one piece to PostgreSQL, Redis or MinIO/S3.
"""

from __future__ import annotations

import os
import secrets
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

GPU_QUEUE = "gpu"


def default_data_dir() -> Path:
    """The per-user data folder (XDG base directories), never the current folder: `keys create`
    run from one folder and `serve` from another must find the same database."""
    return Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share") / "fluidnexus"


class Settings(BaseSettings):
    """One object shared by the API, the worker and the `fluidnexus` service commands."""

    model_config = SettingsConfigDict(env_prefix="FLUIDNEXUS_", env_file=".env", extra="ignore")

    data_dir: Path = Field(
        default_factory=default_data_dir,
        description="default $XDG_DATA_HOME/fluidnexus (~/.local/share/fluidnexus): the same folder wherever "
        "`serve` and `keys` run from",
    )
    database_url: str | None = Field(default=None, description="SQLAlchemy URL; default sqlite in data_dir")
    broker_url: str | None = Field(default=None, description="Celery broker; default kombu filesystem in data_dir")
    broker_key_prefix: str = Field(default="", description="Redis key namespace, so deployments can share a Redis")

    storage_backend: Literal["local", "s3"] = "local"
    storage_dir: Path | None = Field(default=None, description="local backend root; default data_dir/storage")
    s3_endpoint: str = "127.0.0.1:9000"
    s3_access_key: str = "minioadmin"
    s3_secret_key: str = "minioadmin"
    s3_bucket: str = "fluidnexus"
    s3_secure: bool = False
    s3_region: str | None = Field(default=None, description="set it to presign without asking the server")
    s3_public_endpoint: str | None = Field(
        default=None, description="host:port that browsers reach for presigned URLs (default s3_endpoint)"
    )
    presign_seconds: int = Field(default=3600, ge=60, le=7 * 24 * 3600)
    signing_key: str | None = Field(
        default=None, description="secret for the API's own signed download URLs; default: data_dir/signing.key"
    )

    # Upload limits: checked before anything is stored.
    max_upload_bytes: int = Field(default=2 * 1024**3, gt=0, description="whole multipart request")
    max_video_bytes: int = Field(default=1024**3, gt=0)
    max_video_seconds: float = Field(default=120.0, gt=0)
    max_video_frames: int = Field(
        default=7200, gt=0, description="frames in one video (120 s at 60 fps), checked in its header before decoding"
    )
    max_videos: int = Field(default=16, gt=0)
    max_predict_frames: int = Field(default=600, gt=0)

    # Limits against overload and oversized input (issue 16; docs/service.md "Limits").
    max_concurrent_requests: int = Field(
        default=8, gt=0, description="API requests inside the app at once; more wait, holding nothing"
    )
    # One checking place per core, at most 4: on 2 cores 4 checks at once each took longer than a
    # client's 10 s under load (issue 36; docs/reliability.md), 2 answered every admitted upload.
    max_concurrent_uploads: int = Field(
        default_factory=lambda: min(4, os.cpu_count() or 1), gt=0,
        description="scene uploads inside the app at once (default: one per core, at most 4)",
    )
    upload_wait_seconds: float = Field(
        default=3.0, gt=0, description="how long an upload waits for one of those places; then a 429 with Retry-After"
    )
    max_uploads_per_owner: int = Field(
        default=2, gt=0, description="one owner's uploads being checked at once (per API process); one more is a 429"
    )
    # Issue 49: a body sent slowly held an upload place for 40 s; now it must keep up this rate.
    min_body_rate: float = Field(
        default=64 * 1024, gt=0,
        description="bytes a second a request body must average once body_grace_seconds have passed; slower is a 408",
    )
    body_grace_seconds: float = Field(
        default=5.0, gt=0, description="how long a request body may take before min_body_rate applies"
    )
    key_cache_seconds: float = Field(
        default=2.0, ge=0, description="an API key found valid is trusted this long without a database lookup "
        "(per API process; a revoked key is refused within it); 0: every request looks its key up"
    )
    max_json_bytes: int = Field(default=64 * 1024, gt=0, description="a JSON request body (job requests)")
    max_cameras_bytes: int = Field(default=4 * 1024**2, gt=0, description="the uploaded cameras file")
    max_cameras: int = Field(default=64, gt=0, description="cameras in one cameras file")
    max_camera_pixels: int = Field(
        default=3840 * 2160, gt=0, description="width x height of one camera (its video has the same size)"
    )
    max_scene_pixels: int = Field(
        default=4 * 3840 * 2160, gt=0, description="width x height summed over a scene's cameras"
    )

    # Per-owner shares (issue 36; docs/service.md "Limits"): far above what one person's normal use
    # reaches, so that one key cannot fill the queue, the database or the disk for everyone.
    max_unfinished_jobs_per_owner: int = Field(
        default=50, gt=0, description="an owner's queued and running jobs; a new one beyond is a 429 with Retry-After"
    )
    max_scenes_per_owner: int = Field(default=200, gt=0, description="an owner's stored scenes; an upload beyond is a 429")
    max_stored_bytes_per_owner: int = Field(
        default=100 * 1024**3, gt=0,
        description="an owner's stored videos and job files (service.quotas.stored_bytes); an upload or job beyond is a 429",
    )
    jobs_in_flight_per_owner: int = Field(
        default=2, gt=0,
        description="an owner's jobs sent to the workers or running at once; the rest wait their turn (service.queue), "
        "so one owner's backlog never starves another's job. Set it to the number of workers",
    )

    # Worker.
    work_dir: Path | None = Field(default=None, description="worker-local run cache; default data_dir/work")
    device: str = Field(default="auto", description="'auto' (cuda when available), 'cpu' or 'cuda:N'")
    worker_torch_threads: int = Field(default=0, ge=0, description="torch threads per worker child; 0 = all cores")
    job_soft_time_limit: int = Field(default=6 * 3600, gt=0, description="seconds; the job fails cleanly")
    job_hard_time_limit: int = Field(default=6 * 3600 + 300, gt=0, description="seconds; the child is killed")
    job_lease_seconds: int = Field(
        default=16, ge=4, description="a running job without a heartbeat this long is taken over (heartbeat: a quarter of it)"
    )
    worker_unresponsive_seconds: int = Field(
        default=60, ge=2,
        description="serve kills and restarts its embedded worker once its heartbeat (every quarter lease) has not "
        "moved this long: a frozen worker (SIGSTOP, a hung driver) is replaced like a dead one",
    )
    max_transient_retries: int = Field(default=3, ge=0)
    max_job_attempts: int = Field(
        default=3, ge=1, description="starts of one job (worker deaths included) before it is failed"
    )
    runners: str | None = Field(
        default=None,
        description="'module:attribute' of a dict replacing the fluidcore job runners; test doubles only",
    )

    webhook_allow_private: bool = Field(
        default=False,
        description="let webhooks reach loopback, private, link-local and metadata addresses (service.webhooks)",
    )

    migrate_on_start: bool = True
    web_dir: Path = Path(__file__).resolve().parents[1] / "web"

    def resolved_data_dir(self) -> Path:
        return self.data_dir.expanduser().resolve()

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.resolved_data_dir() / 'fluidnexus.sqlite3'}"

    def resolved_broker_url(self) -> str:
        return self.broker_url or "filesystem://"

    def broker_folder(self) -> Path:
        """Message folder of the embedded filesystem broker (used only when no broker_url is set)."""
        return self.resolved_data_dir() / "broker"

    def resolved_storage_dir(self) -> Path:
        return (self.storage_dir or self.resolved_data_dir() / "storage").expanduser().resolve()

    def resolved_work_dir(self) -> Path:
        return (self.work_dir or self.resolved_data_dir() / "work").expanduser().resolve()

    def is_embedded_broker(self) -> bool:
        return self.resolved_broker_url().startswith("filesystem://")


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings (tests build their own `Settings` and pass them to `create_app`)."""
    return Settings()


KEY_FILE = "signing.key"


def signing_key(settings: Settings) -> bytes:
    """The configured key, else the data dir's key file (created on first use, readable by the owner only)."""
    if settings.signing_key:
        return settings.signing_key.encode()
    path = settings.resolved_data_dir() / KEY_FILE
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another process created it first
            return Path(path).read_text().strip().encode()
        with os.fdopen(fd, "w") as handle:
            handle.write(secrets.token_hex(32))
    return path.read_text().strip().encode()
