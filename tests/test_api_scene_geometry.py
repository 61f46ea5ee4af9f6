"""Scene geometry over HTTP: a clip uploaded without a camera file (fov instead, as
`fluidnexus cameras single`), and what a client needs to place a ball."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import create_key
from api.database import session_scope
from api.models import Scene
from api.settings import Settings
from fluidcore import cameras
from fluidcore.cameras.single import single_camera
from service_support import RecordingQueue, sqlite_url, write_video


@pytest.fixture
def client(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    settings = Settings(data_dir=tmp_path / "data", database_url=sqlite_url(tmp_path))
    with TestClient(create_app(settings, queue=RecordingQueue())) as test_client:
        with session_scope(test_client.app.state.sessionmaker) as session:
            auth = {"Authorization": f"Bearer {create_key(session, 'alice')}"}
        yield test_client, auth
        test_client.app.state.engine.dispose()


def _clip(tmp_path: Path, name: str = "phone.mp4") -> tuple[str, tuple[str, bytes, str]]:
    return ("video", (name, write_video(tmp_path / name, width=48, height=64).read_bytes(), "video/mp4"))


def test_upload_with_fov_instead_of_a_camera_file(client, tmp_path: Path) -> None:
    http, auth = client
    response = http.post("/v1/scenes", files=[_clip(tmp_path)], data={"fov": "50", "distance": "2", "up": "up"}, headers=auth)
    assert response.status_code == 201, response.text
    scene = response.json()
    assert scene["cameras"] == ["phone"]
    with session_scope(http.app.state.sessionmaker) as session:
        key = session.get(Scene, scene["id"]).cameras_key
    http.app.state.storage.get_file(key, tmp_path / "stored.json")
    expected, box = single_camera("phone", 48, 64, 50.0, 2.0, "up")
    stored = cameras.load(tmp_path / "stored.json")["phone"]  # the CLI's camera for the same parameters
    assert stored.fx == pytest.approx(expected.fx) and stored.file_path == "phone.mp4"
    assert [list(b) for b in cameras.scene_box(tmp_path / "stored.json")] == [list(b) for b in box]


@pytest.mark.parametrize(
    ("data", "videos", "message"),
    [
        ({}, 1, "give either a cameras file or fov"),
        ({"fov": "0.1"}, 1, "cameras: fov must be between"),
        ({"fov": "50", "up": "north"}, 1, "cameras: up must be one of"),
        ({"fov": "50"}, 2, "exactly one video"),
    ],
)
def test_fov_upload_errors_are_422(client, tmp_path: Path, data: dict, videos: int, message: str) -> None:
    http, auth = client
    parts = [_clip(tmp_path, f"v{i}.mp4") for i in range(videos)]
    response = http.post("/v1/scenes", files=parts, data=data, headers=auth)
    assert response.status_code == 422 and message in response.text, response.text
