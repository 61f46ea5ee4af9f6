"""Fixtures of the web UI's tests: an in-process API over SQLite and PostgreSQL (tests.support.api)
and the browser, web/ as static files and the screenshots' folder (tests.support.browser)."""

from tests.support.api import scene_dir, scene_id, service, sqlite_service  # noqa: F401  fixtures
from tests.support.browser import browser, screens, static_web  # noqa: F401  fixtures
from tests.support.service import postgres_url  # noqa: F401  fixture
