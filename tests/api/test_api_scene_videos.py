"""A scene's uploaded videos served back (`GET /v1/scenes/{id}/videos/{camera}`,
api.routers.scenes): the footage the results page plays beside the reconstruction. The bytes are
the upload's own, byte ranges answer 206 so a <video> seeks, another owner gets a 404, a name that
is no camera of the scene is refused, and the scene's `presigned_url` plays without a key.
SQLite and PostgreSQL."""

from __future__ import annotations

from pathlib import Path

from tests.support.api import Service, upload


def test_the_owner_gets_each_uploaded_video_back_byte_for_byte(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    scene = upload(service, alice, scene_dir).json()
    for camera in ("cam0", "cam1"):
        answer = service.client.get(f"/v1/scenes/{scene['id']}/videos/{camera}", headers=alice)
        assert answer.status_code == 200, answer.text
        assert answer.content == scene_dir[camera].read_bytes()
        assert answer.headers["content-type"] == "video/mp4" and answer.headers["accept-ranges"] == "bytes"
        assert answer.headers["content-disposition"] == f'inline; filename="{camera}.mp4"'
        assert scene["videos"][camera]["url"] == f"/v1/scenes/{scene['id']}/videos/{camera}"


def test_a_range_request_is_answered_206_with_exactly_those_bytes(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    scene_id = upload(service, alice, scene_dir).json()["id"]
    data = scene_dir["cam1"].read_bytes()
    url = f"/v1/scenes/{scene_id}/videos/cam1"
    for header, (start, end) in (("bytes=10-99", (10, 99)), ("bytes=-32", (len(data) - 32, len(data) - 1)),
                                 (f"bytes={len(data) - 5}-", (len(data) - 5, len(data) - 1))):
        part = service.client.get(url, headers={**alice, "Range": header})
        assert part.status_code == 206, (header, part.text)
        assert part.content == data[start:end + 1], header
        assert part.headers["content-range"] == f"bytes {start}-{end}/{len(data)}"
        assert part.headers["content-length"] == str(end - start + 1)
    outside = service.client.get(url, headers={**alice, "Range": f"bytes={len(data)}-"})
    assert outside.status_code == 416 and outside.headers["content-range"] == f"bytes */{len(data)}"


def test_another_owner_and_no_key_get_nothing(service: Service, scene_dir: dict[str, Path]) -> None:
    alice, bob = service.key("alice"), service.key("bob")
    scene_id = upload(service, alice, scene_dir).json()["id"]
    theirs = service.client.get(f"/v1/scenes/{scene_id}/videos/cam0", headers=bob)
    assert theirs.status_code == 404 and theirs.json()["detail"] == f"scene {scene_id} not found"  # not even that it exists
    assert service.client.get(f"/v1/scenes/{scene_id}/videos/cam0").status_code == 401
    forged = service.client.get(f"/v1/scenes/{scene_id}/videos/cam0", params={"expires": 4102444800, "signature": "0" * 64})
    assert forged.status_code == 403


def test_a_camera_name_is_checked_and_must_be_one_of_the_scenes(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    scene_id = upload(service, alice, scene_dir).json()["id"]
    unknown = service.client.get(f"/v1/scenes/{scene_id}/videos/cam7", headers=alice)  # a good name, no camera of it
    assert unknown.status_code == 404
    assert unknown.json()["detail"] == f"scene {scene_id} has no video of camera 'cam7'; its cameras: cam0, cam1"
    for bad in ("..cam0", "cam0%00", ".hidden", "con", "cam0%20"):
        refused = service.client.get(f"/v1/scenes/{scene_id}/videos/{bad}", headers=alice)
        assert refused.status_code == 422, (bad, refused.text)
        assert refused.json()["detail"].startswith("camera: ") and "is not an accepted name" in refused.json()["detail"]
    escaped = service.client.get(f"/v1/scenes/{scene_id}/videos/cam0%2F..%2F..%2Ftransforms.json", headers=alice)
    assert escaped.status_code == 404 and escaped.json()["detail"].startswith("no route")  # a '/' never reaches the route


def test_the_scenes_presigned_url_plays_without_a_key_and_only_that_video(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    scene_id = upload(service, alice, scene_dir).json()["id"]
    listed = service.client.get(f"/v1/scenes/{scene_id}/videos", headers=alice).json()
    assert [item["camera"] for item in listed["items"]] == ["cam0", "cam1"] and listed["scene_id"] == scene_id
    links = {item["camera"]: item for item in listed["items"]}
    assert links["cam0"]["url"] == f"/v1/scenes/{scene_id}/videos/cam0"
    signed = links["cam0"]["presigned_url"]
    assert signed.startswith(links["cam0"]["url"] + "?")
    played = service.client.get(signed, headers={"Range": "bytes=0-15"})
    assert played.status_code == 206 and played.content == scene_dir["cam0"].read_bytes()[:16]
    other = signed.replace("/videos/cam0", "/videos/cam1")  # a link is for its own video only
    assert service.client.get(other).status_code == 403
    assert service.client.get(links["cam1"]["presigned_url"]).content == scene_dir["cam1"].read_bytes()
    assert service.client.get(f"/v1/scenes/{scene_id}/videos", headers=service.key("bob")).status_code == 404


def test_a_range_of_thousands_of_digits_is_416_and_the_video_still_plays(service: Service, scene_dir: dict[str, Path]) -> None:
    """Issue 49 item 3: a 4,301-digit position was a 500 (Python's int() digit limit) on the
    scene's videos and their presigned URLs, which need no key. Past 2^63-1 bytes it is a 416."""
    alice = service.key("alice")
    scene_id = upload(service, alice, scene_dir).json()["id"]
    data = scene_dir["cam0"].read_bytes()
    url = f"/v1/scenes/{scene_id}/videos/cam0"
    signed = service.client.get(f"/v1/scenes/{scene_id}/videos", headers=alice).json()["items"][0]["presigned_url"]
    huge = "9" * 4301
    for header in (f"bytes={huge}-", f"bytes=0-{huge}", f"bytes=-{huge}", f"bytes={2**63}-"):
        for target, headers in ((url, alice), (signed, {})):
            answer = service.client.get(target, headers={**headers, "Range": header})
            assert answer.status_code == 416, (header[:20], answer.text[:200])
            assert answer.headers["content-range"] == f"bytes */{len(data)}" and len(answer.json()["detail"]) < 200
    leading_zeros = service.client.get(url, headers={**alice, "Range": f"bytes={'0' * 5000}3-{'0' * 5000}9"})
    assert leading_zeros.status_code == 206 and leading_zeros.content == data[3:10]
    assert service.client.get(url, headers=alice).content == data
