"""`fluidnexus serve` (API + embedded worker) and `fluidnexus keys create | list | revoke`.

Both read the same settings (`FLUIDNEXUS_*` environment variables, `--data-dir`), so a key
created here is valid for the server started on the same data dir. Nothing here imports
torch: the embedded worker is a separate process that does.
"""

from __future__ import annotations

import ctypes
import functools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from fluidnexus.reporting import user_errors

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from service.queue import CeleryQueue
    from service.settings import Settings
    from service.worker_beats import BeatWatch

DataDir = Annotated[
    Path | None,
    typer.Option("--data-dir", help="database, storage and broker folder (default $FLUIDNEXUS_DATA_DIR, else ~/.local/share/fluidnexus)"),
]
WORKER_STOP_TIMEOUT_S = 30
PR_SET_PDEATHSIG = 1  # linux/prctl.h
RESTART_DELAYS_S = (1.0, 30.0)  # first restart after 1 s, doubling up to 30 s while it keeps dying at boot
WORKER_NICE = 19  # the embedded worker yields the CPU to the API and its upload checks (pool children inherit it;
# at 10, beside checks at 10, a realistic upload under load timed out: docs/reliability.md, issue 36)
# Longer than clients keep an idle connection (httpx and browsers: 5 s or more), so the server
# never closes one just as a client reuses it (a "server disconnected" error under load).
KEEP_ALIVE_S = 20


def _settings(data_dir: Path | None) -> Settings:
    from service.settings import Settings

    settings = Settings(data_dir=data_dir) if data_dir is not None else Settings()
    settings.resolved_data_dir().mkdir(parents=True, exist_ok=True)
    return settings


def serve(
    host: Annotated[str, typer.Option(help="interface to listen on")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port")] = 8000,
    data_dir: DataDir = None,
    worker: Annotated[bool, typer.Option(help="start an embedded worker process with the server")] = True,
) -> None:
    """Run the API (and, by default, one embedded worker) on this machine; stops both on Ctrl-C."""
    import uvicorn

    from api.app import create_app
    from service.queue import CeleryQueue, requeue_orphans

    settings = _settings(data_dir)
    queue = CeleryQueue(settings)
    with _database(settings) as sessions:  # migrates
        if worker and settings.is_embedded_broker():
            orphans = requeue_orphans(sessions, queue)
            if orphans:
                typer.echo(f"resuming {len(orphans)} job(s) left running by the last server: {', '.join(orphans)}", err=True)
    supervisor = WorkerSupervisor(settings, queue) if worker else None
    # uvicorn re-raises SIGTERM after its graceful shutdown; the default action would end this
    # process before the `finally` below stops the worker.
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        app = create_app(settings.model_copy(update={"migrate_on_start": False}), queue=queue)  # migrated above
        uvicorn.run(app, host=host, port=port, timeout_keep_alive=KEEP_ALIVE_S)
    finally:
        if supervisor is not None:
            supervisor.stop()


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(0)


class WorkerSupervisor:
    """Starts the embedded worker and starts it again, with back-off, whenever it dies (a SIGKILL,
    an out-of-memory kill) or stops responding: otherwise its jobs would wait forever while the
    API looks healthy. A worker that stops responding (its heartbeat row, beaten by its pool child
    every quarter lease while the Celery main process keeps time, has not moved for
    `worker_unresponsive_seconds`: a SIGSTOP of either process, a hung driver call) is SIGKILLed
    with its pool children, and then handled like a dead one; the job
    it ran was queued again by the API's reaper once its lease expired ("waiting to resume"),
    and the fence in service.leases keeps the frozen runner from writing anything if it wakes.

    On a death it kills what is left of the worker's process group, removes the dead worker's
    heartbeat (so /readyz answers 503 until the new one beats) and, with the embedded broker,
    sends the jobs it left running again at once (`requeue_orphans`: only this worker takes
    the embedded broker's jobs) instead of waiting out their lease; the queued jobs whose
    prefetched message died with it are sent again by the API's reaper (service.queue)."""

    def __init__(self, settings: Settings, queue: CeleryQueue) -> None:
        from service.database import make_engine, make_sessionmaker

        self.settings, self.queue = settings, queue
        self.engine = make_engine(settings.resolved_database_url(), pool_size=1)
        self.sessions = make_sessionmaker(self.engine)
        self._stopping = threading.Event()
        self.process = _start_worker(settings.resolved_data_dir())
        self._thread = threading.Thread(target=self._watch, name="worker-supervisor", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        delay = RESTART_DELAYS_S[0]
        while True:
            started = time.monotonic()
            code = self._wait_for_exit()
            if self._stopping.is_set():
                return
            # A worker that ran a while before dying starts the back-off again; one dying at boot backs off.
            if time.monotonic() - started > RESTART_DELAYS_S[-1]:
                delay = RESTART_DELAYS_S[0]
            typer.echo(f"embedded worker {self.process.pid} died (exit {code}); restarting in {delay:.0f} s", err=True)
            self._clean_up_after(self.process.pid)
            if self._stopping.wait(delay):
                return
            self.process = _start_worker(self.settings.resolved_data_dir())
            delay = min(delay * 2, RESTART_DELAYS_S[-1])

    def _wait_for_exit(self) -> int:
        """The worker's exit code once it exits; it is killed first if it stops responding."""
        from service.worker_beats import BeatWatch

        timeout = self.settings.worker_unresponsive_seconds
        watch = BeatWatch(timeout)
        while True:
            try:
                return self.process.wait(self.settings.job_lease_seconds / 4)  # the beat's period
            except subprocess.TimeoutExpired:
                pass
            if not self._stopping.is_set() and self._unresponsive(watch):
                typer.echo(f"embedded worker {self.process.pid} stopped responding (no heartbeat for {timeout} s); "
                           "killing it", err=True)
                try:
                    os.killpg(self.process.pid, signal.SIGKILL)  # the frozen pool child with it
                except ProcessLookupError:
                    pass

    def _unresponsive(self, watch: BeatWatch) -> bool:
        from service.database import session_scope
        from service.worker_beats import last_beat, worker_name

        try:
            with session_scope(self.sessions) as session:
                beat = last_beat(session, worker_name(self.process.pid))
        except Exception:  # database down: the worker cannot beat either; judge once it is back
            watch.unreadable()
            return False
        return watch.unresponsive(beat, time.monotonic())

    def _clean_up_after(self, pid: int) -> None:
        from service.queue import requeue_orphans
        from service.worker_beats import forget, worker_name

        try:
            os.killpg(pid, signal.SIGKILL)  # its pool children, if any outlived it
        except ProcessLookupError:
            pass
        try:
            forget(self.sessions, worker_name(pid))
            if self.settings.is_embedded_broker():
                orphans = requeue_orphans(self.sessions, self.queue)
                if orphans:
                    typer.echo(f"resuming {len(orphans)} job(s) the worker left running: {', '.join(orphans)}", err=True)
        except Exception as exc:  # database or broker down: the API's reaper sends them once the lease ends
            typer.echo(f"could not hand the dead worker's jobs back now ({exc}); the reaper will", err=True)

    def stop(self) -> None:
        self._stopping.set()
        _stop_worker(self.process)
        self._thread.join(WORKER_STOP_TIMEOUT_S)
        if self.process.poll() is None:  # restarted just as the server stopped
            _stop_worker(self.process)
        self.engine.dispose()


def _start_worker(data_dir: Path) -> subprocess.Popen[bytes]:
    """One Celery worker on the `gpu` queue, concurrency 1 (one job at a time on this machine),
    at a lower CPU priority than the API (`WORKER_NICE`)."""
    env = {**os.environ, "FLUIDNEXUS_DATA_DIR": str(data_dir), "FLUIDNEXUS_EMBEDDED_WORKER": "1"}  # worker.tasks.EMBEDDED
    command = [
        sys.executable, "-m", "celery", "-A", "worker.tasks", "worker", "--queues", "gpu", "--concurrency", "1",
        "--pool", "prefork", "--loglevel", "INFO", "--without-gossip", "--without-mingle", "--without-heartbeat",
        "--hostname", f"embedded-{os.getpid()}@%h",
    ]
    # Its own process group: a Ctrl-C meant for the server does not also hit the worker mid-boot,
    # and stopping signals the worker's pool children along with it.
    die_with_server = functools.partial(_die_with_parent, os.getpid()) if sys.platform.startswith("linux") else None
    return subprocess.Popen(command, env=env, start_new_session=True, preexec_fn=die_with_server)


def _die_with_parent(parent_pid: int) -> None:
    """Runs in the worker's process before it execs Celery: the kernel SIGKILLs it when the server
    dies, however it dies (`kill -9` included), and Celery's pool children die with it (they
    ask the same of their parent). Otherwise a killed server leaves its worker running a job
    that the next server's worker would start again beside it. It also lowers the worker's CPU
    priority: a job's torch threads must not starve the API's event loop on a small machine."""
    os.nice(WORKER_NICE)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:  # the server died before the line above took effect
        os._exit(1)


def _stop_worker(process: subprocess.Popen[bytes]) -> None:
    """Warm shutdown (the running job's checkpoints are already in storage), then kill the group if it hangs."""
    process.terminate()  # Celery's warm shutdown stops its own pool children
    try:
        process.wait(WORKER_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        typer.echo(f"worker did not stop in {WORKER_STOP_TIMEOUT_S} s; killing it", err=True)
    try:
        os.killpg(process.pid, signal.SIGKILL)  # whatever is left of the group (pool children)
    except ProcessLookupError:
        pass
    process.wait()


def keys_create(
    owner: Annotated[str, typer.Option(help="who the key belongs to; their scenes and jobs are private to them")],
    data_dir: DataDir = None,
) -> None:
    """Create an API key and print it (the only time it is shown; the database keeps a salted hash)."""
    from api.auth import InvalidOwner, create_key
    from service.database import session_scope

    with user_errors(InvalidOwner), _database(_settings(data_dir)) as sessions, session_scope(sessions) as session:
        key = create_key(session, owner)
    typer.echo(key)


def keys_list(
    owner: Annotated[str | None, typer.Option(help="only this owner's keys")] = None,
    data_dir: DataDir = None,
) -> None:
    """List key ids, owners and dates (never the keys themselves: only their hashes are stored)."""
    from sqlalchemy import select

    from service.database import session_scope
    from service.models import ApiKey

    with _database(_settings(data_dir)) as sessions, session_scope(sessions) as session:
        query = select(ApiKey).order_by(ApiKey.created_at)
        for key in session.scalars(query.where(ApiKey.owner == owner) if owner else query):
            revoked = f"revoked {key.revoked_at:%Y-%m-%d %H:%M}" if key.revoked_at else "active"
            typer.echo(f"{key.id}  {key.owner}  created {key.created_at:%Y-%m-%d %H:%M}  {revoked}")


def keys_revoke(
    key_id: Annotated[str, typer.Argument(help="the id shown by `keys list` (the part after fnx_)")],
    data_dir: DataDir = None,
) -> None:
    """Revoke a key: requests with it answer 401 from now on (within key_cache_seconds, 2 s, on a running server)."""
    from api.auth import UnknownKey, revoke_key
    from service.database import session_scope

    with user_errors(UnknownKey), _database(_settings(data_dir)) as sessions, session_scope(sessions) as session:
        row = revoke_key(session, key_id)
        typer.echo(f"revoked {row.id} ({row.owner})")


@contextmanager
def _database(settings: Settings) -> Iterator[sessionmaker[Session]]:
    """Sessions on the settings' database, migrated to the latest schema first."""
    from service.database import make_engine, make_sessionmaker, migrate

    url = settings.resolved_database_url()
    migrate(url)
    engine = make_engine(url)
    try:
        yield make_sessionmaker(engine)
    finally:
        engine.dispose()


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add `serve` and the `keys` group to the top-level app."""
    app.command("serve")(serve)
    keys = typer.Typer(help="API keys: create, list, revoke.", no_args_is_help=True)
    keys.command("create")(keys_create)
    keys.command("list")(keys_list)
    keys.command("revoke")(keys_revoke)
    app.add_typer(keys, name="keys")
