"""The whole generalisation protocol on one scene folder with ground-truth videos (issue 12).

    fluidnexus bench generalise SCENE_DIR [--input-view view_02 --observed 0:90] [--future 60] [--source X,Y,Z[,R]]
        [--quality preview] [--set FIELD=JSON] [--score-every 3] [--score-long-side 240]
        [--tasks nvs,input,future,velocity,whatif,rise] [--figure per_frame.png] [--json]

Only the input view's video reaches the reconstruction (frames A..B-1); every other camera's
frames are read afterwards, for scoring. Tasks (each next to the baselines of the same frames,
computed in the same run):

    nvs       the reconstruction from every other camera with truth, frames A..B-1
              baselines: blank (the background colour estimated from the input view),
              copy_input (the input frame at the same t shown as that view)
    input     the reconstruction from the input view itself (input-view fit; shown next to nvs:
              a fit far above the novel views means the 3D is wrong where no camera looks), and
              the reconstruction's own per-frame fit and one-step forecast of the input view
    future    prediction from frame B-1, frames B..B+F-1, every camera with truth
              baselines: blank, freeze (the input view's frame B-1 held, on every view); and the
              plume width in the input view at frame B+30 (120 on dev scene D): the smoke's extent
              across the image row at the truth plume's mid-height, prediction vs truth
    velocity  mean end-point error (world units/s) of the run's velocity field as its motion model
              reports it (the carrier's air; the paper model's particles, interpolated), at the
              truth's sample points (voxels with density > 0.05, or the synth's particles), at
              every saved frame of the observed and predicted windows; baseline: zero velocity;
              reference: the truth's own axisymmetric mean flow (bench/flow_reference.py), the
              least error of a model without eddies. With it, the plume's head: the 0.98 quantile
              of the particles' height along up against the truth's (HEAD_FRAMES, world units)
    whatif    per counterfactual variant beside the scene (wind / ball, from the protocol.json beside
              it where there is one, else from each variant's gt/meta.json):
              the reconstruction branched at the variant's branch frame, continued once with the
              intervention and once without it (the "own factual prediction" baseline), both
              scored against the variant's truth on its window and on its late window; and the
              effect score: the cosine between the predicted effect (what-if - own factual) and
              the true one (variant truth - factual truth), pixels of the late window, all views
              (1: the intervention changes the images as it does in truth, 0: unrelated, < 0:
              the opposite; from the frames already rendered for the PSNR)
    rise      the first 10 reconstructed frames continued to frame A+60 by prediction: the plume's
              top height above the source against the truth's (a 10-frame reconstruction must rise)

PSNR / SSIM as the shared anchors (scikit-image conventions: per frame, mean over frames, then
over views). `--score-every K` scores every K-th frame of each window and `--score-long-side`
renders and downsizes the truth to that long side: both make a run fit a small machine; the
baselines are always computed on the same frames at the same size. Reader per layout:
bench/gt_scenes.py.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import typer

if __package__ in (None, ""):  # `python bench/generalise.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.gt_scenes import TOP_QUANTILE, GroundTruth, Variant, open_scene  # noqa: E402
from bench.predict import per_frame  # noqa: E402
from bench.scene_args import SET_HELP, quality_overrides  # noqa: E402
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, QUALITY_HELP  # noqa: E402
from fluidnexus.reporting import UserError, echo_json, user_errors  # noqa: E402

TASKS = ("nvs", "input", "future", "velocity", "whatif", "rise")
RISE_OBSERVED = 10  # frames of the short reconstruction the rise task continues
RISE_AT = 60  # frames after the observed window's start at which the plume's top is compared
PLUME_WIDTH_AFTER = 30  # frames after B: issue 23's plume width is measured at frame 120 of dev scene D (B = 90)
# a pixel is smoke where a channel differs from the background colour by more than this (of 255):
# 5 % of full scale, above 8-bit rounding and the soft edge of the renders; set once, not per scene
SMOKE_LEVEL = 13
VELOCITY_MEASURES = ("epe", "zero_epe", "axisymmetric_epe")  # per saved frame; summaries average each
HEAD_FRAMES = (15, 90)  # the saved frames whose head height error is averaged (issue 46: f15-f90)
Predictor = Callable[[Any, list[int], tuple[int, int]], Any]  # (camera, frames, size) -> uint8 (T, H, W, 3)


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def command(
    scene_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="Scene folder with transforms.json and ground truth."),
    input_view: str | None = typer.Option(None, "--input-view", help="The one camera whose video is reconstructed (default: the scene's protocol.json)."),
    observed: str | None = typer.Option(None, "--observed", help="A:B, the observed frames, end exclusive (default: the scene's protocol.json)."),
    future: int | None = typer.Option(None, "--future", min=1, help="Frames to predict after B (default: up to 60, as many as the truth has)."),
    quality: str = typer.Option(DEFAULT_QUALITY, "--quality", help=f"Reconstruction quality: {QUALITY_HELP}."),
    set_: list[str] = typer.Option([], "--set", help=SET_HELP),
    score_every: int = typer.Option(1, "--score-every", min=1, help="Score every K-th frame of each window."),
    score_long_side: int | None = typer.Option(None, "--score-long-side", min=16, help="Score at this long side (default: full size)."),
    tasks: str = typer.Option(",".join(TASKS), "--tasks", help="Comma-separated subset of " + ",".join(TASKS) + "."),
    reconstruction: Path | None = typer.Option(None, "--reconstruction", help="Reuse this finished reconstruction run."),
    source: str | None = typer.Option(None, "--source", help="X,Y,Z[,R]: give the reconstruction this source (world units), as a user who knows their rig would; a diagnostic, not the protocol."),
    out: Path | None = typer.Option(None, "--out", help="Keep the runs here (default: a temporary folder)."),
    figure: Path | None = typer.Option(None, "--figure", help="Write the per-frame PSNR figure (PNG) here."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch threads (default: all cores)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    import torch

    from fluidcore.jobs import parse_frames
    from fluidcore.spec.source_hint import parse_source

    with user_errors():
        hint = None if source is None else parse_source(source)
        if hint is not None and reconstruction is not None:
            raise UserError("--source applies to a new reconstruction; --reconstruction reuses one that has its own")
        if threads is not None:
            torch.set_num_threads(threads)
        chosen = _tasks(tasks)
        gt = open_scene(scene_dir)
        input_view, observed = _protocol_defaults(gt, input_view, observed)
        input_path = gt.input_path(input_view)
        window = parse_frames(observed)
        if window[1] > gt.n_frames:
            raise UserError(f"--observed {observed}: the scene has {gt.n_frames} frames")
        n_future = min(future or 60, gt.n_frames - window[1])
        if "future" in chosen and n_future < 1:
            raise UserError(f"--observed {observed}: no frame after it has ground truth to predict")
        folder = out or Path(tempfile.mkdtemp(prefix="bench-generalise-"))
        protocol = Protocol(gt, input_view, input_path, window, score_every, score_long_side, folder, hint)
        result = protocol.run(chosen, n_future, reconstruction, quality, quality_overrides(set_), progress_bar=not json_out)
        result.update({"threads": torch.get_num_threads(), "load_average": list(os.getloadavg())})
        if figure is not None:
            result["figure"] = str(plot(result, figure))
    if json_out:
        echo_json(result)
    else:
        print_table(result)


def _protocol_defaults(gt: GroundTruth, input_view: str | None, observed: str | None) -> tuple[str, str]:
    """--input-view and --observed as given, else as the scene's protocol.json says."""
    protocol = gt.protocol or {}
    if input_view is None:
        input_view = protocol.get("input_view")
    if observed is None and "observed" in protocol:
        observed = "{}:{}".format(*protocol["observed"])
    if input_view is None or observed is None:
        raise UserError("--input-view and --observed are needed: the scene has no protocol.json that names them")
    return input_view, observed


def _tasks(text: str) -> list[str]:
    chosen = [t.strip() for t in text.split(",") if t.strip()]
    unknown = sorted(set(chosen) - set(TASKS))
    if unknown or not chosen:
        raise UserError(f"--tasks: choose from {', '.join(TASKS)}, got {text!r}")
    return chosen


class Protocol:
    """One scene, one input view, one observed window: runs and scores the tasks."""

    def __init__(
        self, gt: GroundTruth, input_view: str, input_path: Path, window: tuple[int, int],
        score_every: int, score_long_side: int | None, folder: Path, source: Any = None,
    ) -> None:
        self.gt, self.input_view, self.input_path, self.window = gt, input_view, input_path, window
        self.source = source  # a SourceHint the reconstruction is given (--source), else None: estimated
        self.every, self.long_side, self.folder = score_every, score_long_side, folder
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, float] = {}  # this process's CPU time: comparable across machine loads

    # -- running --------------------------------------------------------------------------------
    def run(self, tasks: Sequence[str], n_future: int, reuse: Path | None, quality: str, overrides: dict, progress_bar: bool) -> dict:
        from fluidcore.runs import Run

        recon = Run.open(self._reconstruct(reuse, quality, overrides, progress_bar))
        out: dict[str, Any] = {
            "scene": str(self.gt.root), "layout": self.gt.kind, "input_view": self.input_view,
            "observed": list(self.window), "score_every": self.every, "score_long_side": self.long_side,
            "quality": recon.settings.quality.model_dump(mode="json"), "physics": recon.scene.to_json()["physics"],
            "source": recon.scene.to_json()["source"], "reconstruction": str(recon.path), "tasks": {},
            "source_given": None if self.source is None else self.source.model_dump(mode="json"),
        }
        frames = self._frames(*self.window)
        held_out = [v for v in self.gt.views() if v != self.input_view]
        if "nvs" in tasks and held_out:
            out["tasks"]["nvs"] = self.score(self.gt, held_out, frames, {
                "method": self._render([recon]), "copy_input": self._copy_input(), "blank": self._blank(recon),
            })
        if "input" in tasks:
            out["tasks"]["input"] = self.score(self.gt, [self.input_view], frames, {
                "method": self._render([recon]), "blank": self._blank(recon),
            })
            out["tasks"]["input"]["reconstruction"] = _fit_and_forecast(recon)
        predicted = None
        if ("future" in tasks or "velocity" in tasks) and n_future > 0:
            predicted = self._timed("predict", lambda: self._predict(recon.path, self.folder / "predict", n_future))
        if "future" in tasks and predicted is not None:
            future = self._frames(self.window[1], self.window[1] + n_future)
            out["tasks"]["future"] = self.score(self.gt, self.gt.views(), future, {
                "method": self._render([predicted]), "freeze": self._freeze(self.window[1] - 1), "blank": self._blank(recon),
            })
            at = min(self.window[1] + PLUME_WIDTH_AFTER, self.window[1] + n_future - 1)
            out["tasks"]["future"]["plume_width"] = self.plume_width(recon, predicted, at)
        if "velocity" in tasks:
            out["tasks"]["velocity"] = self.velocity([recon, *([predicted] if predicted else [])])
        if "whatif" in tasks:
            out["tasks"]["whatif"] = {v.name: self.whatif(recon, v) for v in self.gt.variants()}
        if "rise" in tasks:
            out["tasks"]["rise"] = self.rise(recon)
        out["seconds"], out["cpu_seconds"] = self.seconds, self.cpu_seconds
        return out

    def _timed(self, name: str, work: Callable[[], Any]) -> Any:
        started, cpu = time.perf_counter(), time.process_time()
        value = work()
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - started
        self.cpu_seconds[name] = self.cpu_seconds.get(name, 0.0) + time.process_time() - cpu
        return value

    def _reconstruct(self, reuse: Path | None, quality: str, overrides: dict, progress_bar: bool) -> Path:
        from fluidcore.reconstruct.job import run_reconstruct
        from fluidcore.spec.reconstruct import get
        from fluidcore.runs import Run

        if reuse is not None:
            run = Run.open(reuse)
            if run.manifest["input_views"] != [self.input_view] or run.frames() != list(range(*self.window)):
                raise UserError(f"--reconstruction: {reuse} is not {self.input_view} over frames {self.window[0]}:{self.window[1]}")
            return reuse
        preset = get(quality).with_overrides(**overrides)
        path = self.folder / "reconstruct"
        _log(f"reconstructing {self.input_view} frames {self.window[0]}:{self.window[1]} at {preset.name}")
        self._timed("reconstruct", lambda: run_reconstruct(
            self.gt.cameras_path, {self.input_view: self.input_path}, path, quality=preset, frames=self.window,
            source=self.source, progress_bar=progress_bar,
        ))
        return path

    def _predict(self, parent: Path, out: Path, frames: int, **interventions: Any) -> Any:
        from fluidcore import predict
        from fluidcore.spec.controls import InteractionParams
        from fluidcore.runs import Run

        _log(f"continuing {parent.name} by {frames} frames {sorted(k for k, v in interventions.items() if v) or ''}")
        if any(interventions.values()):
            return Run.open(predict.run_interact(parent, out, InteractionParams(**interventions), frames=frames))
        return Run.open(predict.run_predict(parent, out, frames=frames))

    def _frames(self, start: int, stop: int) -> list[int]:
        return list(range(start, stop, self.every))

    def _size(self, camera: Any) -> tuple[int, int]:
        from fluidcore.cameras import render_size

        return render_size(camera.width, camera.height, self.long_side) if self.long_side else (camera.width, camera.height)

    # -- predictors: (camera, frames, size) -> uint8 (T, H, W, 3) --------------------------------
    def _render(self, runs: Sequence[Any]) -> Predictor:
        """Each frame from the first of `runs` that holds it (a continuation, then its parent)."""
        import numpy as np

        from fluidcore.run_frames import render_frames

        def predict(camera: Any, frames: list[int], size: tuple[int, int]) -> np.ndarray:
            scaled = camera.scaled(*size)
            out = []
            for t in frames:
                run = next((r for r in runs if t in r.frames()), None)
                if run is None:
                    raise UserError(f"frame {t}: none of the runs holds it")
                out.append(render_frames(run, scaled, [t])[0])
            return np.stack(out)

        return predict

    def _input_frames(self, frames: list[int], size: tuple[int, int]) -> Any:
        from bench.gt_scenes import read_frames_at

        return read_frames_at(self.input_path, frames, size)

    def _copy_input(self) -> Predictor:
        return lambda camera, frames, size: self._input_frames(frames, size)

    def _freeze(self, t: int) -> Predictor:
        import numpy as np

        def predict(camera: Any, frames: list[int], size: tuple[int, int]) -> np.ndarray:
            last = self._input_frames([t], size)
            return np.broadcast_to(last, (len(frames), *last.shape[1:]))

        return predict

    def _blank(self, run: Any) -> Predictor:
        import numpy as np

        from fluidcore.run_frames import to_uint8_rgb

        colour = to_uint8_rgb(np.asarray(run.background_color, np.float32)[None, None])

        def predict(camera: Any, frames: list[int], size: tuple[int, int]) -> np.ndarray:
            return np.broadcast_to(colour, (len(frames), size[1], size[0], 3))

        return predict

    # -- scoring ---------------------------------------------------------------------------------
    def score(self, gt: GroundTruth, views: Sequence[str], frames: list[int], predictors: dict[str, Predictor]) -> dict:
        """Per view and predictor: mean PSNR / SSIM and the per-frame PSNR; means over views."""
        import numpy as np

        per_view: dict[str, Any] = {}
        for view in views:
            camera = gt.cameras[view]
            size = self._size(camera)
            truth = gt.truth(view, frames, size)
            per_view[view] = {}
            for name, predictor in predictors.items():
                scores = per_frame(predictor(camera, frames, size), truth)
                per_view[view][name] = {"psnr": float(np.mean(scores["psnr"])), "ssim": float(np.mean(scores["ssim"])),
                                        "per_frame_psnr": scores["psnr"]}
            _log(f"  {view}: " + ", ".join(f"{k} {v['psnr']:.2f}" for k, v in per_view[view].items()))
        return {"frames": frames, "views": per_view, "mean": _means(per_view, predictors)}

    def plume_width(self, recon: Any, predicted: Any, t: int) -> dict:
        """The prediction's and the truth's smoke width across the input view at frame t, in the
        row at the truth plume's mid-height (`plume_widths`); the background is the colour the
        reconstruction estimated from the input view (the blank baseline's)."""
        camera = self.gt.cameras[self.input_view]
        size = self._size(camera)
        method = self._render([predicted])(camera, [t], size)[0]
        truth = self.gt.truth(self.input_view, [t], size)[0]
        background = self._blank(recon)(camera, [t], size)[0, 0, 0]
        widths = plume_widths(method, truth, background)
        _log(f"  plume width at frame {t} ({self.input_view}): {widths}")
        return {"frame": t, "view": self.input_view, **widths}

    def velocity(self, runs: Sequence[Any]) -> dict:
        """End-point error per saved truth frame the runs hold, against zero velocity and against
        the truth's own axisymmetric mean flow at the scene's kernel radius (bench/flow_reference.py:
        what a model with the mean flow exactly right and no eddies would score); and the head
        height's error where the truth has one (`_head`)."""
        import numpy as np

        from bench.flow_reference import axisymmetric_mean_flow

        rows = {}
        for t in self.gt.velocity_frames():
            run = next((r for r in runs if t in r.frames()), None)
            truth = self.gt.velocity(t) if run is not None else None
            if truth is None or len(truth[0]) == 0:
                continue
            points, expected = truth
            predicted = _model_velocity(run, t, points)
            reference = axisymmetric_mean_flow(points, expected, np.asarray(run.scene.up), run.scene.physics.h)
            rows[str(t)] = {"epe": _epe(predicted, expected), "zero_epe": _epe(0.0, expected),
                            "axisymmetric_epe": _epe(reference, expected), "head_error": self._head(run, t),
                            "samples": len(points), "window": "observed" if t < self.window[1] else "future"}
        summary = {}
        for part in ("observed", "future"):
            chosen = [r for r in rows.values() if r["window"] == part]
            if chosen:
                summary[part] = {k: float(np.mean([r[k] for r in chosen])) for k in VELOCITY_MEASURES}
        first = rows.get(str(self.window[1]))
        if first is not None:
            summary["first_future_frame"] = {"frame": self.window[1], **{k: first[k] for k in VELOCITY_MEASURES}}
        heads = [abs(r["head_error"]) for t, r in rows.items() if r["head_error"] is not None
                 and HEAD_FRAMES[0] <= int(t) <= HEAD_FRAMES[1]]
        if heads:
            summary["head_error"] = {"frames": list(HEAD_FRAMES), "mean_abs": float(np.mean(heads)), "max_abs": float(np.max(heads))}
        return {"frames": rows, "summary": summary}

    def _head(self, run: Any, t: int) -> float | None:
        """The run's plume head at frame t (the 0.98 quantile of its particles' height along up)
        minus the truth's (`GroundTruth.top_height`, the same quantile of its smoke voxels); None
        without a truth height or particles."""
        import numpy as np

        truth = self.gt.top_height(t)
        state = run.read_frame(t)
        heights = state.positions[state.alive] @ np.asarray(run.scene.up, dtype=np.float32)
        if truth is None or not len(heights):
            return None
        return float(np.quantile(heights, TOP_QUANTILE)) - truth

    def whatif(self, recon: Any, variant: Variant) -> dict:
        """The variant's intervention and the own factual prediction, both against its truth."""
        branch = _branch(recon, variant.branch_frame, self.folder / f"branch_{variant.branch_frame:04d}")
        n = variant.scene.n_frames - 1 - variant.branch_frame
        wind = variant.wind  # the truth's acceleration field, based at its own world height
        intervened = self._timed("whatif", lambda: self._predict(branch.path, self.folder / f"whatif_{variant.name}", n,
                                                                 wind=wind, ball=variant.ball))
        factual = self._timed("whatif", lambda: self._predict(branch.path, self.folder / f"factual_{variant.branch_frame:04d}", n))
        frames = self._frames(variant.first_frame, variant.scene.n_frames)
        method, own_factual = _kept(self._render([intervened, branch])), _kept(self._render([factual, branch]))
        scored = self.score(variant.scene, variant.scene.views(), frames, {
            "method": method, "own_factual": own_factual, "blank": self._blank(recon),
        })
        scored["late_start"] = variant.late_start
        scored["late_mean"] = _means(scored["views"], ("method", "own_factual", "blank"), [t >= variant.late_start for t in frames])
        scored["effect"] = self.effect(variant, frames, method, own_factual)
        scored["intervention"] = {"wind": wind, "ball": variant.ball}
        return scored

    def effect(self, variant: Variant, frames: list[int], method: Predictor, own_factual: Predictor) -> dict:
        """The what-if effect score (module docstring) over the late window of `frames`, all
        views together and per view; a cosine is None where an effect is nothing at all."""
        import numpy as np

        late = [i for i, t in enumerate(frames) if t >= variant.late_start]
        late_frames = [frames[i] for i in late]
        totals = np.zeros(3)  # predicted . true, |predicted|^2, |true|^2
        per_view = {}
        for view in variant.scene.views():
            camera = variant.scene.cameras[view]
            size = self._size(camera)
            predicted = method(camera, frames, size)[late].astype(np.float64) - own_factual(camera, frames, size)[late]
            true = variant.scene.truth(view, late_frames, size).astype(np.float64) - self.gt.truth(view, late_frames, size)
            sums = np.array([np.vdot(predicted, true), np.vdot(predicted, predicted), np.vdot(true, true)], dtype=np.float64)
            totals += sums
            per_view[view] = _cosine(sums)
        return {"cosine": _cosine(totals), "views": per_view, "frames": late_frames}

    def rise(self, recon: Any) -> dict | None:
        """Continue the first RISE_OBSERVED reconstructed frames to frame A + RISE_AT; compare the
        plume's top height above the source with the truth's (None without truth heights)."""
        import numpy as np

        at = self.window[0] + RISE_AT
        last = self.window[0] + RISE_OBSERVED - 1
        source = self.gt.source_height()
        truth = self.gt.top_height(at)
        if truth is None or source is None or last not in recon.frames():
            return None
        branch = _branch(recon, last, self.folder / f"branch_{last:04d}")
        run = self._timed("rise", lambda: self._predict(branch.path, self.folder / "rise", at - last))
        state = run.read_frame(at)
        heights = state.positions[state.alive] @ np.asarray(run.scene.up, dtype=np.float32)
        top = float(np.quantile(heights, 0.98)) if len(heights) else float("nan")
        ratio = (top - source) / (truth - source)
        return {"frame": at, "observed_frames": RISE_OBSERVED, "top_above_source": top - source,
                "truth_top_above_source": truth - source, "ratio": ratio}


def smoke_mask(frame: Any, background: Any) -> Any:
    """(H, W) bool: where a uint8 (H, W, 3) frame differs from the background colour (3,) by more
    than SMOKE_LEVEL in some channel. Not `fluidcore.reconstruct.images.smoke_mask`, which masks an
    input video in units of its own noise: this one scores a render and the truth with one fixed
    level for both, so neither's noise (a render has none) moves the comparison."""
    import numpy as np

    difference = np.abs(np.asarray(frame, np.int16) - np.asarray(background, np.int16).reshape(1, 1, 3))
    return difference.max(axis=-1) > SMOKE_LEVEL


def plume_widths(method: Any, truth: Any, background: Any) -> dict:
    """Widths in pixels (leftmost to rightmost smoke pixel) of the method's and the truth's smoke
    in one image row: the truth plume's mid-height, halfway between its highest and lowest smoke
    row; ratio = method / truth (None where the truth has no smoke in that row or at all)."""
    import numpy as np

    truth_mask, method_mask = smoke_mask(truth, background), smoke_mask(method, background)
    rows = np.flatnonzero(truth_mask.any(axis=1))
    if not len(rows):
        return {"row": None, "method": None, "truth": None, "ratio": None}
    row = int(rows[0] + rows[-1]) // 2

    def width(mask: Any) -> int:
        cols = np.flatnonzero(mask[row])
        return int(cols[-1] - cols[0] + 1) if len(cols) else 0

    widths = {"method": width(method_mask), "truth": width(truth_mask)}
    return {"row": row, **widths, "ratio": widths["method"] / widths["truth"] if widths["truth"] else None}


def _means(per_view: dict[str, Any], names: Sequence[str], keep: Sequence[bool] | None = None) -> dict[str, Any]:
    """Mean PSNR / SSIM over views (per-view means first); with `keep`, PSNR over the kept frames only."""
    import numpy as np

    out = {}
    for name in names:
        if keep is None:
            out[name] = {m: float(np.mean([v[name][m] for v in per_view.values()])) for m in ("psnr", "ssim")}
        else:
            out[name] = {"psnr": float(np.mean([np.mean([p for p, k in zip(v[name]["per_frame_psnr"], keep, strict=True) if k])
                                                for v in per_view.values()]))}
    return out


def _kept(predictor: Predictor) -> Predictor:
    """`predictor`, answering a repeated question (camera, frames, size) from memory: the effect
    score reads the frames the PSNR rendered."""
    memory: dict[tuple, Any] = {}

    def predict(camera: Any, frames: list[int], size: tuple[int, int]) -> Any:
        key = (camera.name, tuple(frames), tuple(size))
        if key not in memory:
            memory[key] = predictor(camera, frames, size)
        return memory[key]

    return predict


def _cosine(sums: Any) -> float | None:
    """a.b / (|a| |b|) from (a.b, |a|^2, |b|^2); None when either is zero (no direction to compare)."""
    dot, aa, bb = (float(v) for v in sums)
    return dot / (aa * bb) ** 0.5 if aa > 0 and bb > 0 else None


def _epe(predicted: Any, expected: Any) -> float:
    """Mean end-point error of `predicted` ((N, 3) or a scalar broadcast) against `expected` (N, 3)."""
    import numpy as np

    return float(np.linalg.norm(predicted - expected, axis=1).mean())


def _model_velocity(run: Any, t: int, points: Any) -> Any:
    """The run's velocity at frame t at `points` (Q, 3), as its motion model reports it
    (`fluidcore.physics.Simulator.velocity_at`: the carrier's air; the paper model's particles,
    Shepard-averaged within 2 kernel radii, 0 where none is near)."""
    import numpy as np
    import torch

    from fluidcore.physics.build import build_simulator
    from fluidcore.smoke import SmokeState

    state = SmokeState.from_frame(run.read_frame(t), "cpu").particles
    with torch.no_grad():
        return build_simulator(run.scene).velocity_at(state, torch.from_numpy(np.ascontiguousarray(points))).numpy()


def _branch(recon: Any, last: int, out: Path) -> Any:
    """The reconstruction's frames up to `last` as a run of their own: exactly what reconstructing
    only those frames writes (each frame depends on earlier ones only), so a continuation can
    start at `last`."""
    from fluidcore.runs import Run

    first = recon.frames()[0]
    if last not in recon.frames():
        raise UserError(f"branch frame {last} is outside the reconstruction ({first}..{recon.frames()[-1]})")
    run = Run.create(
        out, kind=recon.kind, cameras=recon.cameras(), input_views=recon.input_views, frame_range=(first, last + 1),
        fps=recon.fps, channels=recon.channels, background_color=recon.background_color, scene=recon.scene,
        settings=recon.settings,
    )
    if recon.background_images() and not run.background_images():
        run.write_background(recon.background_images())
    for t in range(run.next_frame(), last + 1):
        log = recon.frame_log(t)
        run.write_frame(t, recon.read_frame(t), log["losses"], log["seconds"])
    return run


def _fit_and_forecast(recon: Any) -> dict[str, float]:
    """The reconstruction's own input-view signals, mean over its frames (working resolution):
    "fit" after each frame's fit, "forecast" of each frame by the state carried from the frame
    before, scored before that frame was fitted (fluidcore.reconstruct.loop). Neither needs a
    held-out camera; a fit far above its forecast paints the view instead of explaining it."""
    import numpy as np

    losses = [frame["losses"] for frame in recon.manifest["frames"]]
    keys = {"fit": "input_psnr", "forecast": "forecast_psnr"}
    return {name: float(np.mean([entry[key] for entry in losses])) for name, key in keys.items() if all(key in e for e in losses)}


# -- output ------------------------------------------------------------------------------------
def _rows(result: dict) -> list[tuple[str, str, dict]]:
    """(task, predictor, {"psnr", "ssim"}) for every scored mean."""
    tasks = result["tasks"]
    rows = []
    for task in ("nvs", "input", "future"):
        for name, value in (tasks.get(task) or {}).get("mean", {}).items():
            rows.append((task, name, value))
    for variant, scored in (tasks.get("whatif") or {}).items():
        for name, value in scored["mean"].items():
            rows.append((f"{variant}", name, value))
        for name, value in scored["late_mean"].items():
            rows.append((f"{variant} late", name, value))
    return rows


def print_table(result: dict) -> None:
    print(f"scene {result['scene']} ({result['layout']}), input {result['input_view']}, observed {result['observed']}, "
          f"every {result['score_every']} frame(s), long side {result['score_long_side'] or 'full'}")
    print(f"{'task':<16} {'predictor':<12} {'PSNR':>7} {'SSIM':>7}")
    for task, name, value in _rows(result):
        ssim = f"{value['ssim']:7.4f}" if "ssim" in value else f"{'':>7}"
        print(f"{task:<16} {name:<12} {value['psnr']:7.2f} {ssim}")
    signals = (result["tasks"].get("input") or {}).get("reconstruction")
    if signals:
        print(f"{'input (own)':<16} " + ", ".join(f"{k} {v:.2f}" for k, v in signals.items()) + " (working resolution, all frames)")
    width = (result["tasks"].get("future") or {}).get("plume_width")
    if width and width["ratio"] is not None:
        print(f"{'plume width':<16} frame {width['frame']} {width['view']}: {width['method']} px vs truth "
              f"{width['truth']} px (ratio {width['ratio']:.2f}, row {width['row']})")
    velocity = result["tasks"].get("velocity")
    for part, v in ((velocity or {}).get("summary") or {}).items():
        if part == "head_error":
            print(f"{'head height':<16} frames {v['frames'][0]}-{v['frames'][1]}: mean |error| {v['mean_abs']:.3f}, "
                  f"largest {v['max_abs']:.3f} (world units)")
            continue
        print(f"{'velocity EPE':<16} {part:<12} {v['epe']:7.3f} (zero velocity {v['zero_epe']:.3f}, "
              f"the truth's axisymmetric mean {v['axisymmetric_epe']:.3f})")
    for variant, scored in (result["tasks"].get("whatif") or {}).items():
        cosine = scored["effect"]["cosine"]
        print(f"{variant + ' effect':<16} cosine {'none' if cosine is None else f'{cosine:.3f}'} "
              "(what-if - own factual vs variant truth - factual truth, late window, all views)")
    rise = result["tasks"].get("rise")
    if rise:
        print(f"rise: top {rise['top_above_source']:.3f} above the source at frame {rise['frame']}, truth "
              f"{rise['truth_top_above_source']:.3f} (ratio {rise['ratio']:.2f})")
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result["seconds"].items()) +
          f"; {result['threads']} threads, load {result['load_average'][0]:.2f}")


def plot(result: dict, path: Path) -> Path:
    """Per-frame PSNR (mean over the task's views) of every predictor, one panel per task."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    tasks = result["tasks"]
    panels = [(name, tasks[name]) for name in ("nvs", "input", "future") if tasks.get(name)]
    panels += [(f"what-if {k}", v) for k, v in (tasks.get("whatif") or {}).items()]
    if not panels:
        raise UserError("--figure: no image task was scored")
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    for ax, (title, scored) in zip(axes[0], panels, strict=True):
        names = next(iter(scored["views"].values())).keys()
        for name in names:
            curve = np.mean([v[name]["per_frame_psnr"] for v in scored["views"].values()], axis=0)
            ax.plot(scored["frames"], curve, label=name)
        if "late_start" in scored:
            ax.axvline(scored["late_start"], color="grey", linestyle=":", linewidth=1)
        ax.set_title(title)
        ax.set_xlabel("frame")
        ax.set_ylabel("PSNR (dB), mean over views")
        ax.legend(fontsize=7)
    fig.suptitle(f"{Path(result['scene']).name}: input {result['input_view']}, observed {result['observed']}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("generalise", command)
