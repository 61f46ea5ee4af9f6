"""`fluidnexus keys create | list | revoke` act on the database the server with the same data dir
uses; only salted hashes are stored."""

from __future__ import annotations

import time
from pathlib import Path

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from api.app import create_app
from service.database import make_engine, make_sessionmaker, session_scope
from service.models import ApiKey
from service.settings import Settings
from fluidnexus.cli import app as cli
from tests.support.service import RecordingQueue

runner = CliRunner()


def keys(*args: str, data_dir: Path) -> tuple[int, str]:
    result = runner.invoke(cli, ["keys", *args, "--data-dir", str(data_dir)])
    return result.exit_code, result.output.strip()


def test_created_key_works_until_revoked(tmp_path: Path) -> None:
    code, key = keys("create", "--owner", "alice", data_dir=tmp_path)
    assert code == 0 and key.startswith("fnx_")
    key_id = key.split("_")[1]

    engine = make_engine(Settings(data_dir=tmp_path).resolved_database_url())
    with session_scope(make_sessionmaker(engine)) as session:
        [row] = session.query(ApiKey).all()
        assert row.id == key_id and row.owner == "alice"
        assert key.split("_", 2)[2] not in (row.secret_hash, row.salt)  # the secret itself is not stored
    engine.dispose()

    with TestClient(create_app(Settings(data_dir=tmp_path), queue=RecordingQueue())) as client:
        auth = {"Authorization": f"Bearer {key}"}
        assert client.get("/v1/jobs", headers=auth).status_code == 200
        code, listing = keys("list", "--owner", "alice", data_dir=tmp_path)
        assert code == 0 and key_id in listing and "active" in listing and key not in listing
        assert keys("revoke", key_id, data_dir=tmp_path)[0] == 0
        revoked = time.monotonic()  # the API process trusts a key it checked for key_cache_seconds (2 s)
        while client.get("/v1/jobs", headers=auth).status_code != 401:
            assert time.monotonic() - revoked < Settings().key_cache_seconds + 1.0
            time.sleep(0.1)
        assert "revoked" in keys("list", data_dir=tmp_path)[1]
        client.app.state.engine.dispose()


def test_bad_owner_and_unknown_key_are_clear_errors(tmp_path: Path) -> None:
    code, output = keys("create", "--owner", "two words", data_dir=tmp_path)
    assert code == 2 and "error: owner must be" in output
    code, output = keys("revoke", "0123456789abcdef", data_dir=tmp_path)
    assert code == 2 and "no API key with id" in output
