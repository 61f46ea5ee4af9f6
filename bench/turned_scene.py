"""A benchmark scene written as a +z-up tool would write it (issue 34): the camera file's world
turned by +90 degrees about x (y -> z, z -> -y), its box too; videos and ground truth linked.

    python bench/turned_scene.py SCENE_DIR OUT_DIR

Only the camera file changes, so every image task (nvs, input, future) scores the same frames;
tasks that read world-space truth (velocity, rise, what-if variants) stay in the original world
and are not comparable. `fluidnexus bench generalise OUT_DIR ...` then measures whether the
reconstruction follows the turned world's up (docs/cameras.md, "World conventions").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluidcore.cameras import scene_box  # noqa: E402

TURN = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def turned(scene: Path, out: Path) -> Path:
    """Write OUT/transforms.json (turned) and link SCENE's other entries into OUT; OUT's path."""
    out.mkdir(parents=True, exist_ok=True)
    data = json.loads((scene / "transforms.json").read_text())
    for frame in data["frames"]:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
        matrix[:3, :3], matrix[:3, 3] = TURN @ matrix[:3, :3], TURN @ matrix[:3, 3]
        frame["transform_matrix"] = matrix.tolist()
    corners = TURN @ np.array(scene_box(scene / "transforms.json")).T
    for key in ("voxel_scale", "voxel_matrix"):
        data.pop(key, None)
    data["scene_box"] = {"min": corners.min(1).tolist(), "max": corners.max(1).tolist()}
    (out / "transforms.json").write_text(json.dumps(data, indent=1))
    for entry in scene.iterdir():
        if entry.name != "transforms.json" and not (out / entry.name).exists():
            (out / entry.name).symlink_to(entry.resolve())
    return out


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python bench/turned_scene.py SCENE_DIR OUT_DIR")
    print(turned(Path(sys.argv[1]), Path(sys.argv[2])))
