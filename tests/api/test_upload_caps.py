"""Size and cost caps on scene uploads, checked before the work (issue 20, items 2, 7 and 9): a
video's size and length from its headers, decoding bounded per frame and in frames, COLMAP zips
counted and sized before unpacking, one cameras part, and Idempotency-Key on uploads. The hostile
files are built here (`bench.upload_attacks`), in a few MB of memory."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import av
import numpy as np
import pytest

from bench.upload_attacks import declared_images_zip, many_images_zip, many_member_zip, png_mov, zip_bomb
from fluidcore.cameras import CameraError, load
from fluidcore.video import VideoError, verify
from service.models import Job, Scene
from tests.support.service import upload_parts, write_transforms, write_video
from tests.support.api import Service, make_service

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def stored(service: Service) -> tuple[int, int, list[str]]:
    return service.count(Scene), service.count(Job), service.storage.list("")


def post(service: Service, headers: dict[str, str], parts: list, **extra: str):  # type: ignore[no-untyped-def]
    return service.client.post("/v1/scenes", files=parts, headers={**headers, **extra})


def test_a_16k_png_frame_is_refused_in_small_memory(tmp_path: Path) -> None:
    """The issue's attack: a 0.7 MB MOV holding one 16000x16000 PNG frame (768 MB as RGB) for a
    32x24 camera, with a true and a lying header. Validated in a child process whose data
    segment is capped at 400 MB: refusing it must not decode the frame (before: 1.6 GB)."""
    write_transforms(tmp_path / "transforms.json", ["cam0"])
    for declared in (None, (32, 24)):
        png_mov(tmp_path / "cam0.mov", (16000, 16000), declared)
        script = (
            "import resource, sys\n"
            "resource.setrlimit(resource.RLIMIT_DATA, (400 << 20, 400 << 20))\n"
            "from pathlib import Path\n"
            "from api.uploads import UploadRejected, validate_scene\n"
            "from service.settings import Settings\n"
            "folder = Path(sys.argv[1])\n"
            "try:\n"
            "    validate_scene(folder, 'transforms.json', {'cam0.mov': 1}, Settings(data_dir=folder / 'data'))\n"
            "except UploadRejected as exc:\n"
            "    print(exc.status_code, exc)\n"
        )
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True,
                              cwd=REPO, timeout=120)
        assert done.returncode == 0, done.stderr[-2000:]
        assert done.stdout.startswith("422 video: cam0.mov:"), done.stdout
        assert "larger than 768 pixels" in done.stdout, done.stdout


def test_a_video_longer_than_the_frame_cap_is_refused_from_its_header(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    """The declared frame count is checked before decoding; decoding counts again (headers lie)."""
    for service in make_service(tmp_path, max_video_frames=5):
        response = post(service, service.key("alice"), upload_parts(scene_dir))  # 6-frame videos
        assert response.status_code == 422
        assert "has 6 frames, more than the limit of 5" in response.json()["detail"]
        assert stored(service) == (0, 0, [])
    video = write_video(tmp_path / "ten.mp4", n_frames=10)
    with pytest.raises(VideoError, match="more than the limit of 4"):
        verify(video, max_frames=4)
    with pytest.raises(VideoError, match="more than the limit of 100 pixels"):
        verify(video, max_pixels=100)


def test_a_video_damaged_after_its_first_frame_is_422(service: Service, tmp_path: Path) -> None:
    """Packets after the first keep their sizes but not their content: the first frame decodes
    (no B-frames, so it needs no later packet), the others do not. Before, the upload was
    accepted and a job on it "succeeded"."""
    rng = np.random.default_rng(0)
    good = tmp_path / "cam0.mp4"
    with av.open(str(good), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.options = {"tune": "zerolatency"}
        for image in rng.integers(0, 255, (30, 48, 64, 3), dtype=np.uint8):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode(None))
    data = bytearray(good.read_bytes())
    with av.open(str(good)) as container:
        packets = [(p.pos, p.size) for p in container.demux(container.streams.video[0]) if p.size]
    for position, size in packets[1:]:
        data[position + 8 : position + size] = rng.integers(0, 256, size - 8, dtype=np.uint8).tobytes()
    bad = tmp_path / "bad" / "cam0.mp4"
    bad.parent.mkdir()
    bad.write_bytes(bytes(data))
    files = {"cameras": write_transforms(tmp_path / "transforms.json", ["cam0"], 64, 48), "cam0": bad}
    response = post(service, service.key("alice"), upload_parts(files))
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith("video: cam0.mp4: damaged video")
    assert stored(service) == (0, 0, [])
    files["cam0"] = good
    assert post(service, service.key("alice"), upload_parts(files)).status_code == 201


def _colmap_parts(archive: Path, scene_dir: dict[str, Path]) -> list:
    parts = upload_parts(scene_dir)
    parts[0] = ("cameras", ("cameras.zip", archive.read_bytes(), "application/zip"))
    return parts


def test_colmap_zips_are_counted_and_sized_before_unpacking(
    service: Service, scene_dir: dict[str, Path], tmp_path: Path
) -> None:
    """Before: 20,000 members cost 26.6 s of API CPU; a 510 kB zip unpacked 500 MiB first."""
    alice = service.key("alice")
    many = many_member_zip(tmp_path / "many.zip", 2_000)
    bomb = zip_bomb(tmp_path / "bomb.zip", 100 << 20)
    assert bomb.stat().st_size < 200_000
    for archive, message in [
        (many, "cameras: cameras.zip: 2000 members, more than the limit of 1000"),
        (bomb, "cameras: cameras.zip: its model files unpack to 100 MiB, more than the limit of 64 MiB"),
    ]:
        response = post(service, alice, _colmap_parts(archive, scene_dir))
        assert response.status_code == 422
        assert response.json()["detail"] == message
    assert stored(service) == (0, 0, [])


def test_colmap_models_declaring_too_many_images_are_422_before_pycolmap(
    service: Service, scene_dir: dict[str, Path], tmp_path: Path
) -> None:
    """Issue 36: 821,732 images in images.txt took 285 s and 1.28 GB; 1e9 declared in images.bin was a 500."""
    alice = service.key("alice")
    for archive, message in [
        (many_images_zip(tmp_path / "images.zip", 3_000), "cameras: images.txt: more than 1,000 images, the limit"),
        (declared_images_zip(tmp_path / "declared.zip", 10**9),
         "cameras: images.bin: declares 1,000,000,000 images, more than the limit of 1,000"),
    ]:
        response = post(service, alice, _colmap_parts(archive, scene_dir))
        assert response.status_code == 422, response.text
        assert response.json()["detail"] == message
    assert stored(service) == (0, 0, [])


def _text_model_zip(path: Path, images: str, points: str = "") -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("sparse/0/cameras.txt", "1 PINHOLE 32 24 38.4 38.4 16 12\n")
        archive.writestr("sparse/0/images.txt", images)
        archive.writestr("sparse/0/points3D.txt", points)
    return path


def test_a_colmap_model_pycolmap_cannot_read_is_a_422_that_keeps_the_servers_own_details(
    service: Service, scene_dir: dict[str, Path], tmp_path: Path
) -> None:
    """Issue 49 item 8: the message named the server's temporary folder (fluidnexus-colmap-...)
    and pycolmap's C++ source line and failed expression; an image of a camera the model lacks
    was not a 422 at all (pycolmap's IndexError)."""
    alice = service.key("alice")
    for archive, reason in [
        (_text_model_zip(tmp_path / "a.zip", "1 x y\n\n"), "a line or record it could not parse"),
        (_text_model_zip(tmp_path / "b.zip", "1 1 0 0 0 0 0 4 1 cam0.png\n\n", "1 a b c\n"), "a line or record it could not parse"),
        (_text_model_zip(tmp_path / "c.zip", "1 1 0 0 0 0 0 4 7 cam0.png\n\n"), "Rig with ID 7 does not exist"),
    ]:
        response = post(service, alice, _colmap_parts(archive, scene_dir))
        assert response.status_code == 422, response.text
        assert response.json()["detail"] == f"cameras: cameras.zip: unreadable COLMAP model: {reason}"
    assert stored(service) == (0, 0, [])


def test_several_models_in_one_zip_are_refused_before_unpacking(tmp_path: Path) -> None:
    archive = many_member_zip(tmp_path / "two.zip", 2)
    with pytest.raises(CameraError, match=r"several COLMAP models \(sparse/0, sparse/1\)"):
        load(archive)


def test_a_member_larger_than_it_declares_is_not_unpacked_past_its_size(tmp_path: Path) -> None:
    """A lying directory (1 MiB of data declared as 100 bytes) fails the CRC check; what the
    declared sizes allow is all that could be written."""
    archive = tmp_path / "liar.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as out:
        out.writestr("sparse/0/cameras.txt", bytes(1 << 20))
        out.writestr("sparse/0/images.txt", "")
    data = bytearray(archive.read_bytes())
    for signature, offset in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):  # local header, central directory
        start = data.index(signature)
        data[start + offset : start + offset + 4] = (100).to_bytes(4, "little")
    archive.write_bytes(bytes(data))
    with pytest.raises(CameraError, match="cannot unpack sparse/0/cameras.txt"):
        load(archive)


def test_a_second_cameras_part_is_422(service: Service, scene_dir: dict[str, Path]) -> None:
    parts = upload_parts(scene_dir)
    parts.insert(1, ("cameras", ("other.json", parts[0][1][1], "application/json")))
    response = post(service, service.key("alice"), parts)
    assert response.status_code == 422
    assert response.json()["detail"] == "cameras: give one cameras file, got 2 cameras parts"
    assert stored(service) == (0, 0, [])


def test_an_upload_with_an_idempotency_key_is_stored_once(service: Service, scene_dir: dict[str, Path]) -> None:
    """A client that timed out retries with the same key: one scene. The same key for a
    different upload is 422 and stores nothing; keys are per owner."""
    alice, bob = service.key("alice"), service.key("bob")
    first = post(service, alice, upload_parts(scene_dir), **{"Idempotency-Key": "k1"})
    again = post(service, alice, upload_parts(scene_dir), **{"Idempotency-Key": "k1"})
    assert first.status_code == again.status_code == 201, again.text
    assert again.json()["id"] == first.json()["id"] and again.headers["Idempotent-Replayed"] == "true"
    assert "Idempotent-Replayed" not in first.headers
    assert service.count(Scene) == 1
    keys = service.storage.list("")

    other = upload_parts(scene_dir)
    other[0] = ("cameras", (other[0][1][0], other[0][1][1] + b" ", "application/json"))  # one byte more
    renamed = service.client.post("/v1/scenes", files=upload_parts(scene_dir), data={"name": "renamed"},
                                  headers={**alice, "Idempotency-Key": "k1"})
    for response in (post(service, alice, other, **{"Idempotency-Key": "k1"}), renamed):
        assert response.status_code == 422
        assert response.json()["detail"] == (
            f"Idempotency-Key 'k1' was already used for a different request (scene {first.json()['id']})"
        )
    assert (service.count(Scene), service.storage.list("")) == (1, keys)

    bobs = post(service, bob, upload_parts(scene_dir), **{"Idempotency-Key": "k1"})
    assert bobs.status_code == 201 and bobs.json()["id"] != first.json()["id"]
    assert json.loads(service.client.get("/v1/scenes", headers=alice).text)["total"] == 1


def test_a_validation_process_that_dies_is_replaced(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    """A decoder that crashes its process answers that upload with a 422, and the next upload
    gets a fresh pool instead of a broken one."""
    import shutil

    from api.uploads import UploadRejected, Validators
    from service.settings import Settings

    for path in scene_dir.values():
        shutil.copy(path, tmp_path / path.name)
    sizes = {f"{name}.mp4": (tmp_path / f"{name}.mp4").stat().st_size for name in ("cam0", "cam1")}
    settings = Settings(data_dir=tmp_path / "data")
    validators = Validators(1)
    try:
        assert validators.check(tmp_path, "transforms.json", sizes, None, settings)[0].n_frames == 6
        crashed = validators._pool
        for process in list(crashed._processes.values()):  # what a segfaulting decoder does to it
            process.kill()
            process.join()
        with pytest.raises(UploadRejected, match="stopped the process that checked them"):
            validators.check(tmp_path, "transforms.json", sizes, None, settings)
        assert validators.check(tmp_path, "transforms.json", sizes, None, settings)[0].n_frames == 6
        assert validators._pool is not crashed
    finally:
        validators.close()


def test_a_clip_without_a_camera_file_is_probed_under_the_camera_pixel_cap(service: Service, tmp_path: Path) -> None:
    """Issue 36: the fov upload decoded its first frame under the built-in 8K cap, not
    `max_camera_pixels`: one 8000x8000 PNG frame cost 1.04 GB. A 5000x5000 frame (under 8K, over
    the 3840x2160 cap, its size in no header) is refused by the decoder's cap, as on the camera-file path."""
    clip = png_mov(tmp_path / "phone.mov", (5000, 5000))
    response = service.client.post("/v1/scenes", files=[("video", ("phone.mov", clip.read_bytes(), "video/quicktime"))],
                                   data={"fov": "50"}, headers=service.key("alice"))
    assert response.status_code == 422, response.text
    assert "first frame does not decode within the limit of 8294400 pixels" in response.json()["detail"]
    assert stored(service) == (0, 0, [])
