"""A job's exports through the service: the worker publishes the VDB sequence (one file per frame)
next to the last frame in every other format, and the API lists and serves each file."""

from __future__ import annotations

from pathlib import Path

from fluidcore.exports import export_artifacts
from tests.support.predict_scenes import plume_run
from service.settings import Settings
from tests.support.service import keyed_client, scene_files, upload_parts
from worker.execution import JobExecutor
from worker.runners import RunInputs


def test_the_api_lists_a_jobs_vdb_sequence(tmp_path: Path) -> None:
    def reconstruct(inputs: RunInputs) -> list[Path]:  # a real run folder, without the fit
        plume_run(inputs.run_dir, frames=3)
        return export_artifacts(inputs.run_dir, inputs.render_dir)

    for http, auth in keyed_client(tmp_path):
        scene = http.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=auth).json()
        job = http.post("/v1/jobs", json={"type": "reconstruct", "scene_id": scene["id"]}, headers=auth).json()["id"]
        settings = Settings(data_dir=tmp_path / "data", work_dir=tmp_path / "work")
        executor = JobExecutor(settings, http.app.state.sessionmaker, http.app.state.storage, {"reconstruct": reconstruct})
        assert executor.run(job) == "succeeded"

        items = http.get(f"/v1/jobs/{job}/artifacts", headers=auth).json()["items"]
        exports = {item["name"]: item for item in items if item["kind"] == "export"}
        sequence = [f"exports/smoke_{t:06d}.vdb" for t in range(3)]
        assert set(sequence) <= set(exports)
        assert {"exports/splats_000002.ply", "exports/density_000002.nrrd"} <= set(exports)
        for name in sequence:
            body = http.get(exports[name]["url"], headers=auth)
            assert body.status_code == 200 and len(body.content) == exports[name]["size"]
            assert body.content[:4] == b" BDV"  # OpenVDB's magic number, little-endian
