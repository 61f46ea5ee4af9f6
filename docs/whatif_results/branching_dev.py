"""Branch the D reconstruction at each variant's own start frame (D_wind: 44, D_ball: 0), run the
what-if and the factual prediction from the same frame, score both against the variant's videos
on the late window (PSNR, SSIM with skimage's 7x7 uniform window), all 5 views.

    python docs/whatif_results/branching_dev.py RECONSTRUCTION_RUN OUT_DIR D_wind D_ball > branching_dev.json

The maintained measurement of the same protocol is `fluidnexus bench generalise` (issue 12);
this script recorded the numbers of docs/whatif.md."""
import json, math, sys, time
from pathlib import Path
import numpy as np, torch
torch.set_num_threads(1)
from fluidcore import run_frames, video
from fluidcore.metrics import psnr, ssim
from fluidcore.predict import run_interact, run_predict
from fluidcore.spec.controls import parse_interaction
from fluidcore.runs import Run

DEV = Path("/work/shared/devdata/phiflow_D")
REC = Path(sys.argv[1]); OUT = Path(sys.argv[2]); OUT.mkdir(parents=True, exist_ok=True)
rec = Run.open(REC)
base = float(np.dot(rec.scene.source["center"], rec.scene.up))
results = {}
for variant in sys.argv[3:]:
    meta = json.loads((DEV / variant / "gt" / "meta.json").read_text())
    if meta["forces"]["wind"]:
        w = meta["forces"]["wind"]
        branch = w["start_frame"] - 1
        # the same field expressed at our source's height: strength * exp(growth * (our base - their base))
        wind = {"direction": w["direction_world"], "strength": w["strength"] * math.exp(w["growth"] * (base - w["source_height_world"])),
                "growth": w["growth"], "profile": "exponential"}
        params = parse_interaction(wind, None); late = (75, 150)
    else:
        o = meta["obstacle"]; branch = o["present_from_frame"]
        params = parse_interaction(None, {"center": o["center_world"], "radius": o["radius"]}); late = (50, 150)
    n = 149 - branch
    t0 = time.time()
    wi = Run.open(run_interact(REC, OUT / f"{variant}_whatif", params, frames=n, from_frame=branch))
    t1 = time.time()
    fa = Run.open(run_predict(REC, OUT / f"{variant}_factual_{branch}", frames=n, from_frame=branch))
    t2 = time.time()
    frames = list(range(*late))
    rows = {}
    for name, cam in rec.cameras().items():
        gt = torch.from_numpy(video.read_frames(DEV / variant / "videos" / f"{name}.mp4", late[0], late[1])).float() / 255
        row = {}
        for label, run in (("whatif", wi), ("own_factual", fa)):
            pred = torch.from_numpy(run_frames.render_frames(run, cam, frames)).float() / 255
            row[label] = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt, window="uniform")}
        rows[name] = row
    mean = {k: {m: float(np.mean([rows[v][k][m] for v in rows])) for m in ("psnr", "ssim")} for k in ("whatif", "own_factual")}
    results[variant] = {"branch_frame": branch, "late": list(late), "intervention": {"wind": None if params.wind is None else params.wind.model_dump(),
                        "ball": None if params.ball is None else params.ball.model_dump()}, "views": rows, "mean": mean,
                        "seconds": {"whatif": t1 - t0, "factual": t2 - t1}}
    print(variant, json.dumps(mean), file=sys.stderr, flush=True)
print(json.dumps({"reconstruction": str(REC), "results": results}, indent=1))
