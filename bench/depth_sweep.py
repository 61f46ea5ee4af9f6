"""Throw-away diagnostic (issue 22, not kept): the identification's misfit against the source's
depth along the input ray, with the radius and buoyancy scaled with the depth.

    python bench/depth_sweep.py SCENE VIEW A B POINTS '[x,y,z]' > out   # '[x,y,z]': the true centre

Runs `prepare` (physics auto) on the input view, then scores the identified optimum moved to
POINTS depths over the box's stretch of the ray, at buoyancy x 0.71 / 1 / 1.41, and 5 other source
seeds at the two ends, the axis guess and the truth's depth. JSON: docs/bench_generalise_results/
i22_depth_misfit_*.json; docs/bench_generalise.md, "Depth as a dimension of the identification".
"""
import json, sys, time
from pathlib import Path
import numpy as np
import torch

torch.set_num_threads(1)
sys.path.insert(0, ".")
import fluidnexus.cli.errors  # noqa: F401 - first: it registers every benchmark
from bench.gt_scenes import open_scene
from bench.source import prepared_source
import fluidcore.reconstruct.identify as ident
from fluidcore.reconstruct.init import ray_in_box

scene, view, a0, a1, npts = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
truth_center = np.array(json.loads(sys.argv[6])) if len(sys.argv) > 6 else None
out = {}
original = ident.identify


def wrapped(observation, config, box, source, up, budget, device="cpu", prior_name="", depths=()):
    t0 = time.time()
    found = original(observation, config, box, source, up, budget, device, prior_name, depths)
    out["identify_s"] = time.time() - t0
    out["identified"] = {k: v for k, v in found.to_json().items() if k != "prior"}
    up_v = np.asarray(up, float) / np.linalg.norm(up)
    search = ident._Search(observation, config, box, source, up_v, budget, device)
    camera = observation.camera
    o = camera.center()
    c = np.asarray(source.center)
    d = np.linalg.norm(c - o)
    near, far = ray_in_box(o, (c - o) / d, np.array(box.lo), np.array(box.hi))
    r = source.radius
    k_lo, k_hi = (np.linalg.norm(near - o) + r) / d, (np.linalg.norm(far - o) - r) / d
    # the identified optimum in candidate form (depth 1)
    size = found.source_radius / source.radius
    lift = float((np.asarray(found.source_center) - c) @ up_v) / source.radius
    a = found.buoyancy
    out["k_range"] = [k_lo, k_hi]
    out["d"] = d
    if truth_center is not None:
        ray = (c - o) / d
        out["k_true"] = float((truth_center - o) @ ray) / d
    rows = []
    for k in np.linspace(k_lo, k_hi, npts):
        row = {"k": float(k), "depth_m_from_estimate": float((k - 1) * d)}
        for f in (2**-0.5, 1.0, 2**0.5):
            t1 = time.time()
            m, age = search.misfit((a * k * f, lift, size, float(k)))
            row[f"misfit_b{f:.2f}"] = m
            row[f"age_b{f:.2f}"] = age
            row["rollout_s"] = time.time() - t1
        rows.append(row)
        print(json.dumps(row), flush=True)
    out["sweep"] = rows
    from dataclasses import replace
    ks = [k_lo, 1.0, k_hi] + ([out["k_true"]] if "k_true" in out else [])
    noise = []
    for k in ks:
        values = []
        for seed in range(5):
            other = ident._Search(observation, config, box, replace(source, seed=1000 + seed), up_v, budget, device)
            values.append(other.misfit((a * k, lift, size, float(k)))[0])
        noise.append({"k": float(k), "misfits": values, "mean": float(np.mean(values)), "std": float(np.std(values, ddof=1))})
        print(json.dumps(noise[-1]), flush=True)
    out["seed_noise"] = noise
    return found


ident.identify = wrapped
gt = open_scene(Path(scene))
center, radius = prepared_source(gt, {view: gt.input_path(view)}, (a0, a1), "preview", "auto")
out.update({"scene": scene, "view": view, "center": center.tolist(), "radius": radius})
print(json.dumps(out))
