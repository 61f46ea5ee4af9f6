"""Hostile and absurd input (issue 16): each answer is a 4xx with a message that serialises, and
nothing is stored. The app runs in-process on SQLite (`test_api.make_service`)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.models import Job, Scene
from fluidcore.spec.controls import WindParams
from tests.support.service import camera_entry, upload_parts, write_video
from tests.support.api import Service, make_service


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def stored(service: Service) -> tuple[int, int, list[str]]:
    return service.count(Scene), service.count(Job), service.storage.list("")


def post_json(service: Service, headers: dict[str, str], raw: str):  # type: ignore[no-untyped-def]
    return service.client.post("/v1/jobs", content=raw, headers={**headers, "Content-Type": "application/json"})


def upload_cameras(service: Service, headers: dict[str, str], scene_dir: dict[str, Path], cameras: bytes):  # type: ignore[no-untyped-def]
    parts = upload_parts(scene_dir)
    parts[0] = ("cameras", ("transforms.json", cameras, "application/json"))
    return service.client.post("/v1/scenes", files=parts, headers=headers)


def transforms(*frames: dict) -> bytes:
    return json.dumps({"frames": list(frames)}).encode()


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_in_json_are_422(service: Service, literal: str) -> None:
    alice = service.key("alice")
    for raw in (
        f'{{"type": "reconstruct", "scene_id": "x", "params": {{"frames": [0, {literal}]}}}}',
        f'{{"type": "interact", "parent_job_id": "x", "params": {{"wind": {{"direction": [1, 0, 0], "strength": {literal}}}}}}}',
        f'{{"type": "predict", "parent_job_id": "x", "note": [{literal}]}}',
    ):
        response = post_json(service, alice, raw)
        assert response.status_code == 422, response.text
        assert literal.lstrip("-") in json.dumps(response.json()["detail"])
    assert stored(service) == (0, 0, [])


def test_deeply_nested_json_is_422(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    depth = 20_000  # 40 kB: under the JSON body limit, far past the parser's recursion limit
    raw = '{"type": "reconstruct", "scene_id": "x", "params": ' + "[" * depth + "]" * depth + "}"
    response = post_json(service, alice, raw)
    assert response.status_code == 422 and "nested too deeply" in response.text
    cameras = b'{"frames": ' + b"[" * depth + b"]" * depth + b"}"
    response = upload_cameras(service, alice, scene_dir, cameras)
    assert response.status_code == 422 and "nested too deeply" in response.json()["detail"]
    assert stored(service) == (0, 0, [])


@pytest.mark.parametrize("query", ["offset=9223372036854775808", "offset=-1", "limit=0", "limit=101", "offset=1000000001"])
def test_out_of_range_paging_is_422(service: Service, query: str) -> None:
    alice = service.key("alice")
    for route in ("/v1/jobs", "/v1/scenes"):
        response = service.client.get(f"{route}?{query}", headers=alice)
        assert response.status_code == 422, response.text
        assert response.json()["detail"][0]["loc"][0] == "query"


def test_camera_pixel_limits_hold_with_or_without_a_video(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    with_videos = [camera_entry("cam0", 32, 24, 0.0), camera_entry("cam1", 32, 24, 0.5)]
    huge_unfilmed = camera_entry("side", 100_000, 100_000, 1.0)  # no video part: rendered only
    response = upload_cameras(service, alice, scene_dir, transforms(*with_videos, huge_unfilmed))
    assert response.status_code == 422
    assert "'side' is 100000x100000, more than the limit" in response.json()["detail"]

    service.app.state.settings.max_scene_pixels = 3 * 32 * 24 - 1  # per scene: three small cameras are one pixel over
    response = upload_cameras(service, alice, scene_dir, transforms(*with_videos, camera_entry("side", 32, 24, 1.0)))
    assert response.status_code == 422 and "per scene" in response.json()["detail"]

    service.app.state.settings.max_cameras = 2
    response = upload_cameras(service, alice, scene_dir, transforms(*with_videos, camera_entry("side", 8, 8, 1.0)))
    assert response.status_code == 422 and "3 cameras" in response.json()["detail"]
    assert stored(service) == (0, 0, [])


def test_cameras_file_size_limit_is_413(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    for service in make_service(tmp_path, max_cameras_bytes=200):
        response = upload_cameras(service, service.key("alice"), scene_dir, scene_dir["cameras"].read_bytes())
        assert response.status_code == 413 and "larger than the limit of 200 bytes" in response.json()["detail"]
        assert stored(service) == (0, 0, [])


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("fl_x", 1e-300, "field of view"),
        ("fl_y", 1e300, "field of view"),
        ("cx", 1e300, "far outside"),
        ("cy", -1e6, "far outside"),
        ("translation", 1e300, "from the origin"),
    ],
)
def test_absurd_intrinsics_and_extrinsics_are_422(
    service: Service, scene_dir: dict[str, Path], field: str, value: float, message: str
) -> None:
    entry = camera_entry("cam1", 32, 24, 0.5)
    if field == "translation":
        entry["transform_matrix"][0][3] = value
    else:
        entry[field] = value
    response = upload_cameras(service, service.key("alice"), scene_dir, transforms(camera_entry("cam0", 32, 24, 0.0), entry))
    assert response.status_code == 422, response.text
    assert "cam1" in response.json()["detail"] and message in response.json()["detail"]
    assert stored(service) == (0, 0, [])


def test_chunked_body_over_the_limit_is_413(tmp_path: Path) -> None:
    for service in make_service(tmp_path, max_upload_bytes=64 * 1024):
        alice = service.key("alice")

        def chunks() -> Iterator[bytes]:  # no Content-Length: the limit is found while streaming
            boundary = b"--b\r\nContent-Disposition: form-data; name=\"video\"; filename=\"cam0.mp4\"\r\n\r\n"
            yield boundary
            for _ in range(64):
                yield b"\0" * 4096

        response = service.client.post(
            "/v1/scenes", content=chunks(), headers={**alice, "Content-Type": "multipart/form-data; boundary=b"}
        )
        assert response.status_code == 413 and "larger than 65536 bytes" in response.json()["detail"]
        response = post_json(service, alice, '{"type": "predict", "parent_job_id": "' + "x" * 70_000 + '"}')
        assert response.status_code == 413
        assert stored(service) == (0, 0, [])


def test_file_path_is_never_resolved_outside_the_upload(
    service: Service, scene_dir: dict[str, Path], tmp_path: Path
) -> None:
    """A camera without w/h may take its size from its video, but only from an uploaded part:
    an existing video elsewhere on the server answers exactly like a missing file."""
    outside = write_video(tmp_path / "secret.mp4", width=32, height=24)
    alice = service.key("alice")
    answers = []
    for file_path in (str(outside), "../../../" + str(outside), "/no/such/file.mp4"):
        entry = camera_entry("cam1", 32, 24, 0.5)
        del entry["w"], entry["h"]
        entry["file_path"] = file_path
        response = upload_cameras(service, alice, scene_dir, transforms(camera_entry("cam0", 32, 24, 0.0), entry))
        assert response.status_code == 422
        answers.append(response.json()["detail"].replace(file_path, "PATH"))
    assert answers[0] == answers[1] == answers[2] and "missing fields w and h" in answers[0]
    assert stored(service) == (0, 0, [])


def test_an_uploaded_video_still_gives_a_camera_its_size(service: Service, scene_dir: dict[str, Path]) -> None:
    """The other side of the confinement: file_path naming an uploaded part is read."""
    entry = camera_entry("cam1", 32, 24, 0.5)
    del entry["w"], entry["h"]
    entry["file_path"] = "cam1.mp4"
    response = upload_cameras(service, service.key("alice"), scene_dir, transforms(camera_entry("cam0", 32, 24, 0.0), entry))
    assert response.status_code == 201, response.text


def test_wind_directions_normalise_without_overflow() -> None:
    wind = WindParams(direction=(1e300, 0.0, 0.0), strength=1.0)
    assert wind.direction == (1.0, 0.0, 0.0)
    for direction in ((0.0, 0.0, 0.0), (1e-320, 0.0, 0.0)):
        with pytest.raises(ValueError, match="non-zero vector"):
            WindParams(direction=direction, strength=1.0)


def test_a_zero_wind_direction_is_422_over_the_api(service: Service) -> None:
    body = {"type": "interact", "parent_job_id": "x", "params": {"wind": {"direction": [1e-320, 0, 0], "strength": 1}}}
    response = service.client.post("/v1/jobs", json=body, headers=service.key("alice"))
    assert response.status_code == 422 and "non-zero vector" in response.text
    assert stored(service) == (0, 0, [])


def test_an_empty_idempotency_key_is_no_key(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    scene_id = service.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=alice).json()["id"]
    body = {"type": "reconstruct", "scene_id": scene_id}
    first = service.client.post("/v1/jobs", json=body, headers={**alice, "Idempotency-Key": ""})
    second = service.client.post("/v1/jobs", json=body, headers={**alice, "Idempotency-Key": ""})
    assert first.status_code == second.status_code == 202
    assert first.json()["id"] != second.json()["id"] and "Idempotent-Replayed" not in second.headers


def test_a_background_plate_is_a_bounded_frame_span(service: Service, scene_dir: dict[str, Path]) -> None:
    """`background_frames` (the plate) is checked like `frames`: reversed or longer than a plate
    needs is a 422 naming the field, and nothing is queued; a span is queued as given."""
    alice = service.key("alice")
    scene_id = service.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=alice).json()["id"]
    jobs = service.count(Job)
    for span, words in (([3, 1], "must be greater than start"), ([0, 10_000], "at most")):
        body = {"type": "reconstruct", "scene_id": scene_id, "params": {"background_frames": span}}
        response = service.client.post("/v1/jobs", json=body, headers=alice)
        assert response.status_code == 422 and "background_frames" in response.text and words in response.text, response.text
    assert service.count(Job) == jobs
    body = {"type": "reconstruct", "scene_id": scene_id, "params": {"background_frames": [0, 1]}}
    response = service.client.post("/v1/jobs", json=body, headers=alice)
    assert response.status_code == 202 and response.json()["params"]["background_frames"] == [0, 1]


def test_common_mistakes_get_messages_that_say_what_to_do(service: Service, scene_dir: dict[str, Path]) -> None:
    """Issue 35: pydantic's and the lookups' own words ("Unable to extract tag using discriminator
    'type'", "Input should be a valid dictionary", "scene  not found") said nothing a client can act on."""
    alice = service.key("alice")
    untyped = service.client.post("/v1/jobs", json={"scene_id": "x"}, headers=alice)
    assert untyped.status_code == 422
    assert untyped.json()["detail"][0]["msg"] == 'the job needs its "type": one of reconstruct, predict, interact, resimulate'
    plain = service.client.post("/v1/jobs", content=b'{"type": "reconstruct", "scene_id": "x"}', headers=alice)
    assert plain.status_code == 422 and "Content-Type: application/json" in plain.json()["detail"][0]["msg"]
    for response, kind in (
        (service.client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": ""}, headers=alice), "scene"),
        (service.client.post("/v1/jobs", json={"type": "predict", "parent_job_id": " "}, headers=alice), "job"),
    ):
        assert response.status_code == 404
        assert response.json()["detail"] == f"{kind} id is empty: give the id of one of your {kind}s (GET /v1/{kind}s lists them)"
    both = service.client.post("/v1/scenes", files=upload_parts(scene_dir), data={"fov": "50"}, headers=alice)
    assert both.status_code == 422 and "give a cameras file or fov, not both" in both.json()["detail"]
    assert stored(service) == (0, 0, [])


def test_json_sent_to_the_upload_says_it_takes_multipart_and_names_the_parts(service: Service, scene_dir: dict[str, Path]) -> None:
    """Issue 48: JSON to POST /v1/scenes answered "Field required" at body.video; a form upload
    without its video keeps pydantic's word (the client already speaks multipart)."""
    alice = service.key("alice")
    sent = service.client.post("/v1/scenes", json={"name": "x", "video": "view_00.mp4"}, headers=alice)
    assert sent.status_code == 422
    message = sent.json()["detail"][0]["msg"]
    assert message.startswith("POST /v1/scenes takes multipart/form-data") and "not application/json" in message, message
    for part in ("video (a file)", "cameras (a file)", "fov", "up", "name", "reconstruct"):
        assert part in message, (part, message)
    form_without_video = service.client.post("/v1/scenes", data={"name": "x", "fov": "40"}, headers=alice)
    assert form_without_video.status_code == 422 and form_without_video.json()["detail"][0]["msg"] == "Field required"
    assert stored(service) == (0, 0, [])


@pytest.mark.parametrize(("body", "wrong", "close", "allowed"), [
    ({"type": "reconstruct", "scene_id": "x", "params": {"qualty": "preview"}}, "qualty", "quality",
     ["air_cells", "background_frames", "frames", "physics", "quality", "source", "world_up"]),
    ({"type": "reconstruct", "scene_id": "x", "paramz": {}}, "paramz", "params", ["params", "scene_id", "type", "webhook"]),
    ({"type": "interact", "parent_job_id": "x", "params": {"frames": 3, "wind": {"direction": [1, 0, 0], "strenth": 1}}},
     "strenth", "strength", ["direction", "growth", "profile", "start_frame", "strength"]),
])
def test_a_misspelt_field_is_named_with_the_fields_allowed_there(
    service: Service, body: dict, wrong: str, close: str, allowed: list[str]
) -> None:
    """Issue 48: "Extra inputs are not permitted" alone left the client guessing the right name."""
    refused = service.client.post("/v1/jobs", json=body, headers=service.key("alice"))
    assert refused.status_code == 422
    [extra] = [e for e in refused.json()["detail"] if e["type"] == "extra_forbidden"]
    assert extra["loc"][-1] == wrong
    message = extra["msg"]
    assert message.startswith(f"Extra inputs are not permitted: {wrong!r} is not a field here (did you mean {close!r}?); allowed: ")
    named = message.rsplit("allowed: ", 1)[1].split(", ")
    assert set(allowed) <= set(named) and wrong not in named, named
    assert service.count(Job) == 0


def test_a_wrong_job_type_lists_the_types(service: Service) -> None:
    """Issue 48: pydantic's "Input tag 'render' found using 'type' does not match any of the
    expected tags" named its own machinery; render and bundle jobs are asked for elsewhere."""
    for sent in ("reconstruction", "render"):
        refused = service.client.post("/v1/jobs", json={"type": sent, "scene_id": "x"}, headers=service.key("alice"))
        assert refused.status_code == 422
        message = refused.json()["detail"][0]["msg"]
        assert message.startswith(f'"type" is {sent!r}, not a job type POST /v1/jobs creates: give one of '
                                  "reconstruct, predict, interact, resimulate"), message
        assert "/videos/NAME" in message and "/bundles" in message
    assert service.count(Job) == 0


def test_the_worlds_up_is_an_axis_in_the_camera_file_and_the_job(service: Service, scene_dir: dict[str, Path]) -> None:
    """A camera file's `up` and fps are checked at upload (422, nothing stored); a stated +z is the
    scene's up before any reconstruction; the reconstruct job's `world_up` takes an axis only."""
    alice = service.key("alice")
    cams = (camera_entry("cam0", 32, 24, 0.0), camera_entry("cam1", 32, 24, 0.5))
    for extra, words in (({"up": "sky"}, "up: 'sky' is not an axis"), ({"up": [0, 1, 1]}, "degrees off the nearest axis"),
                         ({"fps": -5}, "fps must be a positive number")):
        body = json.dumps({"frames": list(cams), **extra}).encode()
        response = upload_cameras(service, alice, scene_dir, body)
        assert response.status_code == 422 and words in response.json()["detail"], response.text
    assert stored(service) == (0, 0, [])
    response = upload_cameras(service, alice, scene_dir, json.dumps({"frames": list(cams), "up": "+z"}).encode())
    assert response.status_code == 201, response.text
    scene_id = response.json()["id"]
    assert service.client.get(f"/v1/scenes/{scene_id}", headers=alice).json()["geometry"]["up"] == [0.0, 0.0, 1.0]
    body = {"type": "reconstruct", "scene_id": scene_id, "params": {"world_up": "up"}}
    response = service.client.post("/v1/jobs", json=body, headers=alice)
    assert response.status_code == 422 and "world_up" in response.text, response.text
    body["params"]["world_up"] = "-z"
    response = service.client.post("/v1/jobs", json=body, headers=alice)
    assert response.status_code == 202 and response.json()["params"]["world_up"] == "-z"


def test_videos_at_different_frame_rates_are_422(service: Service, scene_dir: dict[str, Path], tmp_path: Path) -> None:
    parts = upload_parts({**scene_dir, "cam1": write_video(tmp_path / "cam1.mp4", fps=25.0)})
    response = service.client.post("/v1/scenes", files=parts, headers=service.key("alice"))
    assert response.status_code == 422, response.text
    assert "all videos must have the same frame rate (cam0.mp4: 30, cam1.mp4: 25)" in response.json()["detail"]
    assert stored(service) == (0, 0, [])
