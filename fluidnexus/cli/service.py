"""`fluidnexus serve` (API + embedded worker) and `fluidnexus keys create`.

Both read the same settings (`FLUIDNEXUS_*` environment variables, `--data-dir`), so a key
created here is valid for the server started on the same data dir. Nothing here imports
torch: the embedded worker is a separate process that does.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Annotated

import typer

from fluidnexus.cli.errors import user_errors

DataDir = Annotated[
    Path | None,
    typer.Option("--data-dir", help="database, storage and broker folder (default ./data or FLUIDNEXUS_DATA_DIR)"),
]
WORKER_STOP_TIMEOUT_S = 30


def _settings(data_dir: Path | None):  # type: ignore[no-untyped-def]
    from api.settings import Settings

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
    from api.database import make_engine, make_sessionmaker, migrate
    from api.queue import CeleryQueue, requeue_orphans

    settings = _settings(data_dir)
    migrate(settings.resolved_database_url())
    queue = CeleryQueue(settings)
    if worker and settings.is_embedded_broker():
        orphans = requeue_orphans(make_sessionmaker(make_engine(settings.resolved_database_url())), queue)
        if orphans:
            typer.echo(f"resuming {len(orphans)} job(s) left running by the last server: {', '.join(orphans)}", err=True)
    process = _start_worker(settings.resolved_data_dir()) if worker else None
    try:
        uvicorn.run(create_app(settings, queue=queue), host=host, port=port)
    finally:
        if process is not None:
            _stop_worker(process)


def _start_worker(data_dir: Path) -> subprocess.Popen[bytes]:
    """One Celery worker on the `gpu` queue, concurrency 1 (one job at a time on this machine)."""
    env = {**os.environ, "FLUIDNEXUS_DATA_DIR": str(data_dir)}
    command = [
        sys.executable, "-m", "celery", "-A", "worker.tasks", "worker", "--queues", "gpu", "--concurrency", "1",
        "--pool", "prefork", "--loglevel", "INFO", "--without-gossip", "--without-mingle", "--without-heartbeat",
        "--hostname", f"embedded-{os.getpid()}@%h",
    ]
    return subprocess.Popen(command, env=env)


def _stop_worker(process: subprocess.Popen[bytes]) -> None:
    """Warm shutdown (the running job's checkpoints are already in storage), then kill if it hangs."""
    process.terminate()
    try:
        process.wait(WORKER_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def keys_create(
    owner: Annotated[str, typer.Option(help="who the key belongs to; their scenes and jobs are private to them")],
    data_dir: DataDir = None,
) -> None:
    """Create an API key and print it (the only time it is shown; the database keeps a salted hash)."""
    from api.auth import InvalidOwner, create_key
    from api.database import make_engine, make_sessionmaker, migrate, session_scope

    settings = _settings(data_dir)
    url = settings.resolved_database_url()
    migrate(url)
    engine = make_engine(url)
    with user_errors(InvalidOwner), session_scope(make_sessionmaker(engine)) as session:
        key = create_key(session, owner)
    engine.dispose()
    typer.echo(key)


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add `serve` and the `keys` group to the top-level app."""
    app.command("serve")(serve)
    keys = typer.Typer(help="API keys.", no_args_is_help=True)
    keys.command("create")(keys_create)
    app.add_typer(keys, name="keys")
