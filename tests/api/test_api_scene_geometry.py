"""Scene geometry over HTTP: a clip uploaded without a camera file (fov instead, as
`fluidnexus cameras single`), and what a client needs to place a ball."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from fluidcore import cameras, scene_info
from fluidcore.cameras.single import single_camera
from fluidcore.runs import ReconstructSettings, Run, SourceEstimateRecord
from fluidcore.spec.physics import PBFConfig, Source
from fluidcore.spec.reconstruct import get
from fluidcore.spec.scene import Scene as RunScene
from fluidcore.spec.solids import SolidBall
from service.database import session_scope
from service.models import Job, JobState, Scene
from service.storage import run_prefix
from tests.support.service import keyed_client, scene_files, upload_parts, write_video


@pytest.fixture
def client(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    yield from keyed_client(tmp_path)


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
    geometry = http.get(f"/v1/scenes/{scene['id']}", headers=auth).json()["geometry"]
    assert geometry["box"] == {"min": list(box[0]), "max": list(box[1])}
    assert geometry["cameras"]["phone"]["center"] == pytest.approx([0.0, 0.0, 2.0])


@pytest.mark.parametrize(
    ("data", "videos", "message"),
    [
        ({}, 1, "cameras: give a cameras file (transforms.json, info.json or a zipped COLMAP model), or fov"),
        ({"fov": "0.1"}, 1, "cameras: fov must be between"),
        ({"fov": "50", "up": "north"}, 1, "cameras: up must be one of"),
        ({"fov": "50"}, 2, "exactly one video"),
        ({"fov": "60", "distance": "1e-300"}, 1, "cameras: distance 1e-300 (with fov 60): its scene box: its smallest side is"),
        ({"fov": "60", "distance": "1e300"}, 1, "cameras: distance 1e+300 (with fov 60): its scene box: a corner is"),
    ],
)
def test_fov_upload_errors_are_422(client, tmp_path: Path, data: dict, videos: int, message: str) -> None:
    http, auth = client
    parts = [_clip(tmp_path, f"v{i}.mp4") for i in range(videos)]
    response = http.post("/v1/scenes", files=parts, data=data, headers=auth)
    assert response.status_code == 422 and message in response.text, response.text


@pytest.mark.parametrize(("box", "message"), [
    ({"min": [0, 0, 0], "max": [1, 0, 1]}, "scene_box: min [0.0, 0.0, 0.0] must be below max [1.0, 0.0, 1.0] on every axis"),
    ({"min": [1, 1, 1], "max": [0, 2, 2]}, "must be below max"),
    ({"min": [-1e308] * 3, "max": [1e308] * 3}, "scene_box: a corner is 1e+308 world units from the origin; at most 1e+06"),
    ({"min": [0, 0, 0], "max": [1e-300] * 3}, "scene_box: its smallest side is 1e-300 world units"),
    ({"min": [1000, 0, 0], "max": [1000.5, 1, 1]}, "needs sides of at least 1"),  # too thin to resolve so far out
])
def test_a_declared_box_the_worker_cannot_use_is_refused_at_upload(client, tmp_path: Path, box: dict, message: str) -> None:
    """Issue 49 item 7: each was a 201 whose reconstruction then failed (min >= max, +-1e308:
    "source.radius ..."; 1e-300: "internal error", a ZeroDivisionError)."""
    http, auth = client
    files = scene_files(tmp_path / "scene")
    declared = json.loads(files["cameras"].read_text())
    files["cameras"].write_text(json.dumps({**declared, "scene_box": box}))
    response = http.post("/v1/scenes", files=upload_parts(files), headers=auth)
    assert response.status_code == 422 and response.json()["detail"].startswith("cameras: transforms.json: scene_box: ")
    assert message in response.json()["detail"], response.text
    assert http.get("/v1/scenes", headers=auth).json()["total"] == 0 and http.app.state.storage.list("") == []


def test_scene_geometry_over_http(client, tmp_path: Path) -> None:
    """Before a reconstruction: the box and cameras of the upload; after: the run's source too."""
    http, auth = client
    files = scene_files(tmp_path / "scene")
    scene = http.post("/v1/scenes", files=upload_parts(files), headers=auth).json()
    geometry = http.get(f"/v1/scenes/{scene['id']}", headers=auth).json()["geometry"]
    loaded = cameras.load(files["cameras"])
    with pytest.raises(cameras.CameraError):  # these test cameras share no bounded view and declare no box
        cameras.frusta_box(loaded)
    assert geometry["box"] is None and geometry["source"] is None and geometry["up"] == [0, 1, 0] and geometry["solids"] == []
    for name, camera in loaded.items():
        assert geometry["cameras"][name]["center"] == pytest.approx(camera.center().tolist())
    assert http.get("/v1/scenes", headers=auth).json()["items"][0]["geometry"] is None  # listings stay light

    # a finished reconstruction given its whole source: its run manifest knows the source
    given = _finished_reconstruction(http, auth, scene["id"], loaded, tmp_path / "given", None)
    geometry = http.get(f"/v1/scenes/{scene['id']}", headers=auth).json()["geometry"]
    assert geometry["box"] == {"min": [0.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}
    assert geometry["source"] == {"center": [0.5, -0.8, 0.0], "radius": 0.1, "depth": None, "job_id": given}
    # its health report: a source 0.1 of a 1-wide box is fine; no frames fitted yet, so no fit check
    checks = {check["name"]: check for check in geometry["health"]["checks"]}
    assert checks["source size"]["level"] == "ok" and checks["source size"]["value"] == pytest.approx(0.2)
    assert "input fit" not in checks and geometry["health"]["warnings"] == []

    # a later one that estimated it from one view: how the depth was found, and the range the view allows
    estimate = SourceEstimateRecord(depth_cue="box axis", depth_range=((0.5, -0.8, 1.0), (0.5, -0.8, -1.0)),
                                    pixels={"cam0": (16.0, 20.0, 2.0)})
    later = _finished_reconstruction(http, auth, scene["id"], loaded, tmp_path / "later", estimate)
    source = http.get(f"/v1/scenes/{scene['id']}", headers=auth).json()["geometry"]["source"]
    assert source["job_id"] == later and source["center"] == [0.5, -0.8, 0.0]
    assert source["depth"] == {"cue": "box axis", "range": [[0.5, -0.8, 1.0], [0.5, -0.8, -1.0]]}
    schema = http.get("/openapi.json").json()["components"]["schemas"]
    assert "depth" in schema["SceneSource"]["properties"] and "range" in schema["SourceDepth"]["properties"]

    # one with a solid ball in its scene: the geometry shows it, and the health report notes that no smoke touched it
    ball = SolidBall(center=(0.5, 0.5, 0.0), radius=0.2)
    _finished_reconstruction(http, auth, scene["id"], loaded, tmp_path / "ball", None, (ball,))
    geometry = http.get(f"/v1/scenes/{scene['id']}", headers=auth).json()["geometry"]
    assert geometry["solids"] == [{"center": [0.5, 0.5, 0.0], "radius": 0.2}]
    (note,) = [check for check in geometry["health"]["checks"] if check["name"] == "solids"]
    assert note["level"] == "note" and note["advice"] == ["solids"] and "params.solids" in note["message"]


def _finished_reconstruction(http, auth, scene_id: str, loaded, folder: Path, estimate, solids=()) -> str:  # noqa: ANN001
    """A reconstruct job of the scene marked succeeded, with a run manifest in storage whose source
    was given whole (`estimate` None) or estimated as `estimate` says, its scene holding `solids`; its job id."""
    run = Run.create(
        folder, kind="reconstruct", cameras=loaded, input_views=["cam0"], frame_range=(0, 2), fps=30.0,
        channels=1, background_color=[0.0], settings=ReconstructSettings(quality=get("preview"), source_estimate=estimate),
        scene=RunScene((0.0, -1.0, -1.0), (1.0, 1.0, 1.0), (0.0, 1.0, 0.0), PBFConfig(h=0.05), Source((0.5, -0.8, 0.0), 0.1, 1),
                       solids=solids),
    )
    job = http.post("/v1/jobs", json={"type": "reconstruct", "scene_id": scene_id}, headers=auth).json()
    http.app.state.storage.put_file(f"{run_prefix(job['id'])}/manifest.json", run.path / "manifest.json")
    with session_scope(http.app.state.sessionmaker) as session:
        row = session.get(Job, job["id"])
        row.state, row.finished_at = JobState.SUCCEEDED, datetime.now(UTC)
    return job["id"]


def test_scene_info_command_matches(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from fluidnexus.cli import app

    files = scene_files(tmp_path / "scene")
    result = CliRunner().invoke(app, ["scene", "info", str(files["cameras"])])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == scene_info.from_cameras_file(files["cameras"])
    (tmp_path / "empty").mkdir()
    result = CliRunner().invoke(app, ["scene", "info", str(tmp_path / "empty")])  # neither a run nor a capture
    assert result.exit_code == 2 and "error:" in result.output
