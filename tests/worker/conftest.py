"""Fixtures of the worker tests: PostgreSQL for the executor tests, Redis and PostgreSQL for the
Celery ones."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.service import REDIS_URL, database_url, port_open, postgres_url  # noqa: F401  postgres_url: a fixture
from tests.support.worker import Deployment


@pytest.fixture
def redis_postgres(tmp_path: Path) -> Iterator[Deployment]:
    if not port_open("127.0.0.1", 6379):
        pytest.skip("Redis is not running on 127.0.0.1:6379 (.ci/run starts it)")
    with database_url("postgres", tmp_path) as url:
        deployment = Deployment(tmp_path, url, REDIS_URL.format(db=0))
        yield deployment
        deployment.engine.dispose()
    import redis

    client = redis.Redis.from_url(REDIS_URL.format(db=0))
    for key in client.scan_iter(f"{deployment.settings.broker_key_prefix}*"):
        client.delete(key)
