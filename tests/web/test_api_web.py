"""What the browser UI needs from the API: its files and the API reference served with no
internet, and particle positions for the 3D what-if view."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from tests.support.service import store_run

from tests.support.api import Service, reconstruct
from fluidcore.spec.simulation import AIR_CELLS

ROOT = Path(__file__).resolve().parents[2]
WEB = ROOT / "web"
EXTERNAL = re.compile(r"""(?:src|href)\s*=\s*["']?(?:https?:)?//""", re.IGNORECASE)
LOCAL_REF = re.compile(r"""(?:src|href)\s*=\s*["'](/[^"']*)["']""", re.IGNORECASE)


@pytest.mark.parametrize("page", ["/docs", "/redoc", "/"])
def test_pages_load_nothing_from_other_hosts(sqlite_service: Service, page: str) -> None:
    """/docs (Swagger UI), /redoc and the UI reference only files this server answers with 200."""
    html = sqlite_service.client.get(page)
    assert html.status_code == 200
    assert not EXTERNAL.search(html.text), EXTERNAL.search(html.text)
    assets = set(LOCAL_REF.findall(html.text))
    assert assets, "the page references no local asset"
    for asset in assets:
        response = sqlite_service.client.get(asset)
        assert response.status_code == 200 and len(response.content) > 0, asset


def test_redoc_draws_no_image_from_a_cdn_and_the_favicon_is_served(sqlite_service: Service) -> None:
    html = sqlite_service.client.get("/redoc").text
    bundle = sqlite_service.client.get(LOCAL_REF.search(html.split("<body>")[1]).group(1))
    assert bundle.status_code == 200 and b"Redoc" in bundle.content
    assert not re.findall(rb"https?://[^\"' ]+\.(?:svg|png|gif|jpe?g)", bundle.content)  # offline: no broken image
    icon = sqlite_service.client.get("/favicon.ico")
    assert icon.status_code == 200 and icon.content[:4] == b"\x00\x00\x01\x00"  # an ICO file


def test_swagger_page_loads_the_bundle_and_the_schema(sqlite_service: Service) -> None:
    html = sqlite_service.client.get("/docs").text
    assert "swagger-ui-bundle.js" in html and "/openapi.json" in html
    assert sqlite_service.client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/particles"]


def test_ui_scripts_import_only_local_modules() -> None:
    """Every ES module import in web/js names a file that exists (no CDN, no bare package names)."""
    imports = []
    for script in sorted((WEB / "js").glob("*.js")):
        for target in re.findall(r"""from\s+["']([^"']+)["']""", script.read_text()):
            imports.append(target)
            assert target.startswith("./") or target.startswith("../"), (script.name, target)
            assert (script.parent / target).resolve().is_file(), (script.name, target)
    assert "../vendor/three.min.js" in imports
    for licence in ("LICENSE-three", "LICENSE-uplot"):
        assert "MIT License" in (WEB / "vendor" / licence).read_text()


# -- particles -------------------------------------------------------------------------------------

def write_states(service: Service, job_id: str, counts: dict[int, int]) -> dict[int, np.ndarray]:
    """A run in storage with one state per frame: `counts[t]` particles, the last one dead."""
    rng = np.random.default_rng(0)
    positions = {t: rng.uniform(-0.5, 0.5, size=(n, 3)).astype(np.float32) for t, n in counts.items()}
    store_run(service.storage, job_id, positions)
    return positions


def test_particles_of_a_frame_with_the_scene_box(service: Service, scene_id: str) -> None:
    alice = service.key("alice")
    job = reconstruct(service, alice, scene_id).json()["id"]
    url = f"/v1/jobs/{job}/particles"
    early = service.client.get(url, headers=alice)
    assert early.status_code == 409 and "no run" in early.json()["detail"]

    positions = write_states(service, job, {3: 50, 4: 40})
    last = service.client.get(url, headers=alice).json()
    assert last["frame"] == 4 and last["frames"] == [3, 4] and last["total"] == 39  # the dead particle left out
    np.testing.assert_allclose(np.reshape(last["positions"], (-1, 3)), positions[4][:39], atol=1e-5)
    assert last["scene"]["box_lo"] == [-0.5, 0.0, -0.5] and last["scene"]["box_hi"] == [0.5, 1.0, 0.5]
    assert last["scene"]["up"] == [0.0, 1.0, 0.0] and last["scene"]["source"]["center"] == [0.0, 0.1, 0.0]
    assert last["air"] is None  # a run without the air grid: still air

    capped = service.client.get(url, params={"frame": 3, "max_points": 10}, headers=alice).json()
    sample = np.reshape(capped["positions"], (-1, 3))
    assert capped["frame"] == 3 and capped["total"] == 49 and len(sample) == 10
    expected = positions[3][np.linspace(0, 48, 10).round().astype(int)]  # evenly spaced, first and last kept
    np.testing.assert_allclose(sample, expected, atol=1e-5)

    missing = service.client.get(url, params={"frame": 7}, headers=alice)
    assert missing.status_code == 404 and "3..4" in missing.json()["detail"]
    assert service.client.get(url, params={"max_points": 10**6}, headers=alice).status_code == 422
    assert service.client.get(url, headers=service.key("bob")).status_code == 404
    assert service.client.get(url).status_code == 401


def test_the_air_saved_with_a_frame_comes_sampled_on_a_lattice(service: Service, scene_id: str) -> None:
    """A run that saves the air: the particles answer carries it at the centres of a lattice over the
    box (5 along the long side), each point's velocity the air's there (world units/s)."""
    from fluidcore.runs import SavedAir

    alice = service.key("alice")
    job = reconstruct(service, alice, scene_id).json()["id"]
    n = 8  # a MAC grid of 8^3 cells over the 1-unit box: x faces (9, 8, 8), y (8, 9, 8), z (8, 8, 9)
    y_faces = np.broadcast_to(np.linspace(0.0, 1.0, n + 1)[None, :, None], (n, n + 1, n)).astype(np.float32)  # v_y = y
    air = SavedAir((np.full((n + 1, n, n), 0.25, np.float32), y_faces.copy(), np.zeros((n, n, n + 1), np.float32)),
                   np.array([-0.5, 0.0, -0.5]), 1.0 / n)
    store_run(service.storage, job, {0: np.zeros((3, 3), np.float32)}, air=air)
    sample = service.client.get(f"/v1/jobs/{job}/particles", headers=alice).json()["air"]
    points, velocities = np.reshape(sample["points"], (-1, 3)), np.reshape(sample["velocities"], (-1, 3))
    assert len(points) == 5**3 and points.min(0).tolist() == [-0.4, 0.1, -0.4] and points.max(0).tolist() == [0.4, 0.9, 0.4]
    np.testing.assert_allclose(velocities[:, 0], 0.25, atol=1e-6)
    np.testing.assert_allclose(velocities[:, 1], points[:, 1], atol=1e-5)  # the air rises faster higher up, as saved
    np.testing.assert_allclose(velocities[:, 2], 0.0, atol=1e-6)


# -- limits and the wind's arrows -------------------------------------------------------------------

def test_the_limits_are_the_parameter_models_json_schema(sqlite_service: Service) -> None:
    """GET /v1/limits (no key: the page reads it before sign-in) holds each field's bounds as the
    job type's parameter model declares them in its JSON Schema, and new frames the server's cap."""
    from service.job_types import JobType

    answer = sqlite_service.client.get("/v1/limits")
    assert answer.status_code == 200
    limits = answer.json()
    assert set(limits) == {t.value for t in JobType if t.writes_run}
    reconstruct = JobType.RECONSTRUCT.params.model_json_schema()["properties"]
    (cells,) = [branch for branch in reconstruct["air_cells"]["anyOf"] if branch.get("type") == "integer"]  # or null: the model's own
    assert {k: limits["reconstruct"]["air_cells"][k] for k in ("minimum", "maximum", "anyOf")} == {
        k: cells[k] for k in ("minimum", "maximum", "anyOf")}
    assert limits["reconstruct"]["motion"]["enum"] == reconstruct["motion"]["enum"] == ["carrier", "paper"]
    assert limits["reconstruct"]["quality"]["enum"] == reconstruct["quality"]["enum"]
    assert limits["reconstruct"]["frames[1]"]["minimum"] == reconstruct["frames"]["anyOf"][0]["prefixItems"][1]["minimum"]
    interact = JobType.INTERACT.params.model_json_schema()
    wind, ball = interact["$defs"]["WindParams"]["properties"], interact["$defs"]["BallParams"]["properties"]
    for field in ("minimum", "maximum", "description"):
        assert limits["interact"]["wind.strength"][field] == wind["strength"][field]
        assert limits["interact"]["wind.growth"][field] == wind["growth"][field]
    assert limits["interact"]["ball.radius"]["exclusiveMinimum"] == ball["radius"]["exclusiveMinimum"]
    assert limits["interact"]["from_frame"]["minimum"] == interact["properties"]["from_frame"]["anyOf"][0]["minimum"]
    max_frames = sqlite_service.app.state.settings.max_predict_frames
    assert limits["interact"]["frames"]["maximum"] == limits["predict"]["frames"]["maximum"] == max_frames
    assert "/v1/limits" in sqlite_service.client.get("/openapi.json").json()["paths"]


def test_the_air_grid_rule_in_the_schema_is_the_models() -> None:
    """The "0 or 8..128" the browser reads (an `anyOf` in the schema) accepts exactly what the
    model accepts for the paper model, checked at the edges of each branch (the carrier refuses 0
    as well, a rule between two fields that its message states)."""
    import jsonschema

    from fluidcore.spec.jobs import ReconstructParams

    validator = jsonschema.Draft202012Validator(ReconstructParams.model_json_schema())
    for cells in (-1, 0, 1, AIR_CELLS[0] - 1, AIR_CELLS[0], AIR_CELLS[1], AIR_CELLS[1] + 1):
        try:
            ReconstructParams(motion="paper", air_cells=cells)
            accepted = True
        except ValueError:
            accepted = False
        assert validator.is_valid({"motion": "paper", "air_cells": cells}) == accepted, cells


def test_the_wind_arrows_come_from_the_one_gain(sqlite_service: Service) -> None:
    """POST /v1/wind/accelerations evaluates `WindParams.gain` above the wind's base height (the
    source's unless it names one); a wind the model refuses is a 422 naming the field."""
    from fluidcore.spec.controls import WindParams

    alice = sqlite_service.key("alice")
    url = "/v1/wind/accelerations"
    wind = {"direction": [1, 0, 0], "strength": 2.0, "growth": 1.5, "profile": "linear"}
    heights = [0.0, 0.2, 0.9]
    answer = sqlite_service.client.post(url, json={"wind": wind, "source_height": 0.2, "heights": heights}, headers=alice)
    assert answer.status_code == 200, answer.text
    model = WindParams(**wind)
    assert answer.json()["accelerations"] == [2.0 * model.gain(h - 0.2) for h in heights]
    placed = sqlite_service.client.post(url, json={"wind": {**wind, "base_height": 0.9}, "source_height": 0.2, "heights": heights},
                                        headers=alice).json()["accelerations"]
    assert placed == [2.0 * model.gain(h - 0.9) for h in heights]
    refused = sqlite_service.client.post(url, json={"wind": {**wind, "profile": "uniform"}, "source_height": 0.0, "heights": [0.0]},
                                         headers=alice)
    assert refused.status_code == 422 and "growth must be 0 for a uniform wind" in refused.text
    overflowing = sqlite_service.client.post(url, json={"wind": wind, "source_height": 0.0, "heights": [1e308]}, headers=alice)
    assert overflowing.status_code == 422 and "heights" in overflowing.text  # never an infinite (null) number
    assert sqlite_service.client.post(url, json={"wind": wind, "source_height": 0.0, "heights": [0.0]}).status_code == 401


def test_the_upload_forms_box_comes_from_the_one_single_camera(sqlite_service: Service) -> None:
    """GET /v1/cameras/single: the box `POST /v1/scenes` makes from `fov`, and its edges where that
    camera sees them (issue 48: the form draws them on the first frame as the field of view is
    typed); a field of view or up the upload would refuse is a 422 naming it."""
    import math

    from fluidcore.cameras.single import single_camera

    alice = sqlite_service.key("alice")
    url = "/v1/cameras/single"
    answer = sqlite_service.client.get(url, params={"width": 300, "height": 400, "fov": 40}, headers=alice)
    assert answer.status_code == 200, answer.text
    _, box = single_camera("video", 300, 400, 40.0)
    assert answer.json()["box"] == {"min": box[0].tolist(), "max": box[1].tolist()}
    edges = answer.json()["edges"]
    assert len(edges) == 12
    # the box's back face: its centre section fills the frame, so at depth 1 + tan(20 deg) it spans 1 / (1 + tan) of it
    shrink = 1 / (1 + math.tan(math.radians(20)))
    back = {(round(u, 6), round(v, 6)) for edge in edges for u, v in edge
            if abs(abs(u - 150) - 150 * shrink) < 1e-6 and abs(abs(v - 200) - 200 * shrink) < 1e-6}
    assert len(back) == 4, edges
    wide = sqlite_service.client.get(url, params={"width": 300, "height": 400, "fov": 120}, headers=alice).json()["edges"]
    assert len(wide) == 8 and all(math.isfinite(x) for edge in wide for end in edge for x in end)  # the front face is behind it
    for params, field in (({"fov": 200}, "fov"), ({"fov": 40, "up": "sideways"}, "up"), ({"fov": 40, "width": 0}, "width")):
        refused = sqlite_service.client.get(url, params={"width": 300, "height": 400, **params}, headers=alice)
        assert refused.status_code == 422 and field in refused.text, refused.text
    assert sqlite_service.client.get(url, params={"width": 300, "height": 400, "fov": 40}).status_code == 401
