"""Fixtures of the API tests: an in-process API over SQLite and PostgreSQL (api_support)."""

from api_support import scene_dir, scene_id, service, sqlite_service  # noqa: F401  fixtures
from service_support import postgres_url  # noqa: F401  fixture
