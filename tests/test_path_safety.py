"""Issue 20, item 1: no string a user sends becomes a file path or a storage key unchecked.

One naming rule (fluidcore.names.check_name) is applied where a name enters (the API: a 422
naming the field; the CLI: `error: ...`, exit 2; the camera readers), and one join
(fluidcore.names.safe_join) refuses any path outside its root. Every hostile form is sent
through every route and command that takes a name: traversal, absolute, percent-encoded, NUL,
backslash and unicode tricks (a fullwidth solidus that NFKC folds to '/', fullwidth letters, a
right-to-left override)."""

from __future__ import annotations

import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from fluidcore import cameras
from fluidcore.cameras import CameraError
from fluidcore.jobs import JobInputError
from fluidcore.names import UnsafeName, UnsafePath, check_name, check_relative, safe_join
from fluidnexus.cli import app
from service.models import Scene
from tests.support.service import camera_entry, scene_files, write_video
from tests.support.api import Service, make_service

HOSTILE = [
    "../x",
    "../../storage/jobs/0123456789abcdef/videos/view_02",
    "/tmp/x",
    "%2e%2e%2fx",
    "..%2fx",
    "a\x00b",
    "..\\..\\x",
    "a\\b",
    "\uff0ftmp\uff0fx",  # FULLWIDTH SOLIDUS: NFKC turns it into '/'
    "\uff0e\uff0e\uff0fx",  # fullwidth '../'
    "\uff43\uff41\uff4d0",  # fullwidth 'cam0': NFKC makes it look like an accepted name
    "cam\u202e4pm.exe",  # RIGHT-TO-LEFT OVERRIDE: displays as another name
    "",
    ".",
    "..",
    ".hidden",
    "-rf",
    "_x",
    "a..b",
    "cam0\n",
    "x" * 65,
    "CON",  # Windows device names, in any case and with any extension
    "nul",
    "Aux.mp4",
    "com1",
    "LPT9.txt",
]
GOOD = ["cam0", "view_02", "a.b-c_d", "0", "X" * 64, "x_", "console", "com10", "nullable", "con_1"]


# -- the rule and the join ---------------------------------------------------------------------------

def test_the_naming_rule_takes_plain_names_and_refuses_every_hostile_form() -> None:
    assert [check_name(name, "camera") for name in GOOD] == GOOD
    for name in HOSTILE:
        with pytest.raises(UnsafeName, match="^camera: "):
            check_name(name, "camera")
    for value in (None, 3, b"cam0", ["cam0"]):
        with pytest.raises(UnsafeName):
            check_name(value, "camera")


def test_relative_paths_are_names_joined_by_slashes() -> None:
    assert check_relative("videos/cam0.mp4", "file_path") == "videos/cam0.mp4"
    for value in ("videos/../../x.mp4", "/videos/cam0.mp4", "videos//cam0.mp4", "./cam0.mp4", "videos/",
                  "a\\b/cam0.mp4", "videos\uff0fcam0.mp4", "/".join(["d"] * 9), *HOSTILE):
        with pytest.raises(UnsafeName, match="^file_path: "):
            check_relative(value, "file_path")


def test_the_join_refuses_every_result_outside_its_root(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "inside").mkdir(parents=True)
    (root / "link").symlink_to(tmp_path)  # a planted link: no name check can see it
    assert safe_join(root, "inside", "cam0.mp4") == (root / "inside" / "cam0.mp4").resolve()
    assert safe_join(root, "inside/cam0.mp4") == (root / "inside" / "cam0.mp4").resolve()
    for parts in (("../x",), ("/tmp/x",), ("inside", "../../x"), ("link", "x"), ("a\x00b",), ("",), (".",),
                  ("inside/../..",)):
        with pytest.raises(UnsafePath):
            safe_join(root, *parts)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["root"]


# -- the camera readers ------------------------------------------------------------------------------

def _transforms(path: Path, names: list[str]) -> Path:
    frames = [{**camera_entry(name, 32, 24, 0.5 * i), "file_path": None} for i, name in enumerate(names)]
    path.write_text(json.dumps({"frames": frames}))
    return path


def test_camera_readers_refuse_hostile_camera_names(tmp_path: Path) -> None:
    for i, name in enumerate(n for n in HOSTILE if n):  # "" has its own message: a non-empty string
        with pytest.raises(CameraError, match=r"frames\[1\]\.camera: .* is not an accepted name"):
            cameras.load(_transforms(tmp_path / f"t{i}.json", ["cam0", name]))
    # named by the stem of file_path when there is no camera field
    frame = {**camera_entry("cam0", 32, 24, 0.0), "file_path": "videos/%2e%2e%2fx.mp4"}
    del frame["camera"]
    (tmp_path / "stem.json").write_text(json.dumps({"frames": [frame]}))
    with pytest.raises(CameraError, match="is not an accepted name"):
        cameras.load(tmp_path / "stem.json")


def test_a_colmap_zip_reads_only_members_with_plain_names(tmp_path: Path) -> None:
    """A member whose folder is a fullwidth lookalike (or holds a backslash) is refused, not read."""
    model = "1 PINHOLE 32 24 38.4 38.4 16 12\n", "1 1 0 0 0 0 0 4 1 cam0.png\n\n"
    for i, folder in enumerate(("\uff53parse/0", "sparse\\0", "sparse/0/..\\..")):
        archive = tmp_path / f"model{i}.zip"
        with zipfile.ZipFile(archive, "w") as zf:
            zf.writestr(f"{folder}/cameras.txt", model[0])
            zf.writestr(f"{folder}/images.txt", model[1])
        with pytest.raises(CameraError, match="not an accepted relative path"):
            cameras.load(archive)


# -- the API -----------------------------------------------------------------------------------------

@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def _stored(service: Service) -> tuple[int, list[str]]:
    return service.count(Scene), [info.key for info in service.storage.list("")]


def _upload(service: Service, headers: dict[str, str], frames: list[dict], videos: dict[str, Path],
            cameras_name: str = "transforms.json"):  # type: ignore[no-untyped-def]
    parts = [("cameras", (cameras_name, json.dumps({"frames": frames}).encode(), "application/json"))]
    parts += [("video", (name, path.read_bytes(), "video/mp4")) for name, path in videos.items()]
    return service.client.post("/v1/scenes", files=parts, headers=headers)


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_video(tmp_path_factory.mktemp("clip") / "clip.mp4")


def test_the_issue_attack_upload_is_refused_and_nothing_is_stored(service: Service, clip: Path, tmp_path: Path) -> None:
    """The upload of issue 20: cameras named `/tmp/x` and a traversal into another owner's job
    folder. Before, it was stored and its reconstruct wrote /tmp/x.mp4 and replaced the other
    owner's view_02.mp4."""
    alice = service.key("alice")
    victim = service.storage.root / "jobs" / "0123456789abcdef" / "videos" / "view_02.mp4"
    victim.parent.mkdir(parents=True)
    victim.write_bytes(b"the other owner's video")
    before = _stored(service)
    traversal = "../../../../storage/jobs/0123456789abcdef/videos/view_02"
    frames = [{**camera_entry("/tmp/x", 32, 24, 0.0), "file_path": "x.mp4"},  # the videos match by file_path
              {**camera_entry(traversal, 32, 24, 0.5), "file_path": "view_02.mp4"}]
    response = _upload(service, alice, frames, {"x.mp4": clip, "view_02.mp4": clip})
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert detail.startswith("cameras: ") and "/tmp/x" in detail and "is not an accepted name" in detail
    assert _stored(service) == before
    assert victim.read_bytes() == b"the other owner's video"
    assert not Path("/tmp/x.mp4").exists()


def test_every_hostile_camera_name_is_a_422_naming_the_field(service: Service, clip: Path) -> None:
    alice = service.key("alice")
    answers = {}
    for name in HOSTILE:
        frame = {**camera_entry(name, 32, 24, 0.5), "file_path": None}
        response = _upload(service, alice, [camera_entry("cam0", 32, 24, 0.0), frame], {"cam0.mp4": clip})
        answers[name] = (response.status_code, response.json()["detail"])
    assert all(status == 422 and detail.startswith("cameras: ") and "camera" in detail
               for status, detail in answers.values()), answers
    assert _stored(service) == (0, [])


def test_every_hostile_file_path_is_a_422_naming_the_field(service: Service, clip: Path) -> None:
    """A cameras file on the server names only its uploaded parts; before, any file_path was
    accepted (only its base name was used to match a video)."""
    alice = service.key("alice")
    answers = {}
    for file_path in ("../../storage/jobs/0123456789abcdef/videos/cam1.mp4", "/tmp/cam1.mp4", "%2e%2e%2fcam1.mp4",
                      "videos\\..\\..\\cam1.mp4", "\uff0ftmp\uff0fcam1.mp4", "videos/../cam1.mp4", "cam1\u202e.mp4"):
        frame = {**camera_entry("cam1", 32, 24, 0.5), "file_path": file_path}
        response = _upload(service, alice, [camera_entry("cam0", 32, 24, 0.0), frame], {"cam0.mp4": clip, "cam1.mp4": clip})
        answers[file_path] = (response.status_code, response.json()["detail"])
    assert all(status == 422 and detail.startswith("cameras: camera 'cam1': file_path: ")
               for status, detail in answers.values()), answers
    assert _stored(service) == (0, [])


def test_every_hostile_part_file_name_is_a_422_naming_the_part(service: Service, clip: Path) -> None:
    """Video and cameras part names are refused as sent; before, a directory part or a traversal
    was silently stripped to the base name and the upload stored. (A Windows path such as
    `C:\\x\\cam0.mp4` never reaches the check: the multipart parser keeps its last part.)"""
    alice = service.key("alice")
    frames = [camera_entry("cam0", 32, 24, 0.0)]
    answers = {}
    for name in ("../cam0.mp4", "../../x/cam0.mp4", "/tmp/cam0.mp4", "%2e%2e%2fcam0.mp4",
                 "\uff0fcam0.mp4", "\uff43am0.mp4", "cam0\u202e.mp4", ".cam0.mp4", "cam0.mp4\n"):
        response = _upload(service, alice, frames, {name: clip})
        answers[("video", name)] = (response.status_code, response.json()["detail"])
        response = _upload(service, alice, frames, {"cam0.mp4": clip}, cameras_name=name.replace("cam0.mp4", "t.json"))
        answers[("cameras", name)] = (response.status_code, response.json()["detail"])
    assert all(status == 422 and detail.startswith(f"{field}: file name: ")
               for (field, _), (status, detail) in answers.items()), answers
    assert _stored(service) == (0, [])


def test_artifact_names_are_looked_up_never_joined(service: Service, clip: Path) -> None:
    """A download name is only compared with the names the worker recorded: a traversal to the
    scene's stored video is a 404, never its bytes."""
    alice = service.key("alice")
    response = _upload(service, alice, [camera_entry("cam0", 32, 24, 0.0)], {"cam0.mp4": clip})
    assert response.status_code == 201, response.text
    scene_id = response.json()["id"]
    job = service.client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": scene_id, "params": {}}, headers=alice)
    job_id = job.json()["id"]
    for name in ("../../../scenes/%s/input/cam0.mp4" % scene_id, "..%2f..%2f..%2fscenes%2f" + scene_id + "%2finput%2fcam0.mp4",
                 "%2e%2e/%2e%2e/%2e%2e/scenes/" + scene_id + "/input/cam0.mp4", "\uff0e\uff0e\uff0fcam0.mp4"):
        response = service.client.get(f"/v1/jobs/{job_id}/artifacts/{name}", headers=alice)
        assert response.status_code == 404, (name, response.status_code)
        assert response.content != clip.read_bytes()


def test_a_camera_whose_video_takes_another_videos_name_is_a_422(service: Service, clip: Path) -> None:
    """A camera named `orbit` (or `refined_cam0` beside `cam0`) passes the naming rule, but its
    MP4 would share a name with another video of the job; before, the job ran to its end and
    failed publishing on the artifact table's unique name."""
    alice = service.key("alice")
    for names in (["cam0", "orbit"], ["cam0", "side_by_side"], ["cam0", "refined_cam0"]):
        frames = [{**camera_entry(name, 32, 24, 0.5 * i), "file_path": None} for i, name in enumerate(names)]
        response = _upload(service, alice, frames, {"cam0.mp4": clip})
        assert response.status_code == 422 and response.json()["detail"].startswith(f"cameras: camera {names[1]!r}: ")
    assert _stored(service) == (0, [])


# -- the CLI -----------------------------------------------------------------------------------------

runner = CliRunner()


def _cli_fails(args: list[str], message: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: ") and message in result.output, result.output


def test_cli_commands_refuse_hostile_names_in_cameras_files_and_views(tmp_path: Path) -> None:
    files = scene_files(tmp_path / "scene")
    for i, name in enumerate(("/tmp/x", "../../x", "\uff0ftmp\uff0fx", "cam\u202e0")):
        evil = _transforms(tmp_path / f"evil{i}.json", ["cam0", name])
        _cli_fails(["scene", "info", str(evil)], "is not an accepted name")
        _cli_fails(["reconstruct", "--cameras", str(evil), "--video", f"cam0={files['cam0']}", "--out",
                    str(tmp_path / f"run{i}")], "is not an accepted name")
        _cli_fails(["reconstruct", "--cameras", str(files["cameras"]), "--video", f"{name}={files['cam0']}",
                    "--out", str(tmp_path / f"run{i}")], "--video: VIEW: ")
        _cli_fails(["cameras", "colmap", "--video", f"{name}={files['cam0']}", "--video", f"cam1={files['cam1']}",
                    "--out", str(tmp_path / f"rig{i}.json")], "--video: VIEW: ")
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("evil")) == ["scene"]


def test_cameras_single_refuses_a_video_whose_stem_is_no_camera_name(tmp_path: Path) -> None:
    video = write_video(tmp_path / "my clip%2f.mp4")
    _cli_fails(["cameras", "single", "--video", str(video), "--fov", "60", "--out", str(tmp_path / "t.json")],
               "is not an accepted name")
    assert not (tmp_path / "t.json").exists()


# -- rendering: the join refuses even a name that got past the checks --------------------------------

def test_render_artifacts_never_writes_outside_its_folder(tmp_path: Path) -> None:
    """A video name that is no video of the run is refused before anything renders (what a
    client asks for is checked against the run's names); a run made before the naming rule,
    with a camera named like a path, is refused by the join, not written next to the output folder."""
    from fluidcore.artifacts import render_artifacts
    from tests.support.run_folder import _camera, _create, _state

    run = _create(tmp_path / "run", frame_range=(0, 1))
    run.write_frame(0, _state(0), {}, 0.0)
    out = tmp_path / "deep" / "out"
    with pytest.raises(JobInputError, match="not a video of this run; have cam, orbit"):
        render_artifacts(run.path, out, ["../../escaped"])
    old = _create(tmp_path / "old", frame_range=(0, 1), cameras={"../../escaped": _camera()}, input_views=["../../escaped"])
    old.write_frame(0, _state(0), {}, 0.0)
    with pytest.raises(UnsafePath):
        render_artifacts(old.path, out, ["../../escaped"])
    assert not (tmp_path / "escaped.mp4").exists() and not (tmp_path / "deep" / "escaped.mp4").exists()
    clash = _create(tmp_path / "clash", frame_range=(0, 1), cameras={"orbit": _camera()}, input_views=["orbit"])
    clash.write_frame(0, _state(0), {}, 0.0)
    with pytest.raises(JobInputError, match="camera 'orbit'"):
        render_artifacts(clash.path, out, ["orbit"])
