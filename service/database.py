"""Engine, sessions and migrations. SQLite (embedded) and PostgreSQL share the same code."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from service.errors import Conflict

ROOT = Path(__file__).resolve().parents[1]
SQLITE_BUSY_MS = 30_000
POOL_TIMEOUT_S = 10


def make_engine(url: str, pool_size: int = 5) -> Engine:
    """An engine; SQLite gets WAL, a busy timeout and foreign keys, since API and worker write at once.

    `pool_size` connections at most, no overflow: the API admits that many requests at once
    (api.middleware.AdmissionLimit), so a wait for a connection means something is wrong and
    ends after POOL_TIMEOUT_S with a 503 rather than stalling every request behind it."""
    pool = {"pool_size": pool_size, "max_overflow": 0, "pool_timeout": POOL_TIMEOUT_S}
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        else:
            pool = {}  # an in-memory database is one connection, not a pool
        engine = create_engine(
            url, connect_args={"timeout": SQLITE_BUSY_MS / 1000, "check_same_thread": False}, **pool
        )
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True, **pool)


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_MS}")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that commits on success and rolls back on any exception."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def commit_or_conflict(session: Session, conflict: str) -> None:
    """Commit a delete whose checks passed; a reference the database refuses at the commit (another
    request stored a row naming what this one deletes after those checks) is a Conflict saying
    `conflict`, with nothing written, instead of a bug."""
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise Conflict(conflict) from None


def migrate(url: str) -> None:
    """`alembic upgrade head` against `url` (the same migrations the `alembic` command runs)."""
    from alembic import command
    from alembic.config import Config

    config = Config(str(ROOT / "alembic.ini"))
    config.set_main_option("script_location", str(ROOT / "migrations"))
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    command.upgrade(config, "head")


def ping(engine: Engine) -> None:
    """Raise if the database does not answer."""
    with engine.connect() as connection:
        connection.execute(text("SELECT 1"))
