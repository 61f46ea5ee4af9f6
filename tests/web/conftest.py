"""Fixtures of the web UI's API tests: an in-process API over SQLite and PostgreSQL (tests.support.api)."""

from tests.support.api import scene_dir, scene_id, service, sqlite_service  # noqa: F401  fixtures
from tests.support.service import postgres_url  # noqa: F401  fixture
