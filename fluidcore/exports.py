"""Exporters: frames of a run, written in formats other tools read (docs/exports.md).

`EXPORTERS` is the one registry, keyed by the format name the CLI (`fluidnexus export
--format`) and the API's artifacts use; adding a format is one entry here.

  npz      the frame's arrays: live physical particles (world units, units/s) and the visual
           Gaussians, as `numpy.savez` (what `fluidnexus export` always wrote);
  ply      the visual Gaussians in the 3D Gaussian splatting PLY layout that splat viewers and
           VFX plug-ins read (x y z, nx ny nz, f_dc_0..2, opacity, scale_0..2, rot_0..3);
  density  the physical density on a voxel grid in world units, as .npz (density, origin,
           spacing), mass conserving: density x voxel volume sums to the particles' mass, with
           the velocity on the same voxels (world units/s, `frame_density`);
  nrrd     the same density grid as a NRRD volume (raw float32, origin and spacing in the
           header), which ParaView, 3D Slicer and Houdini's NRRD readers open;
  velocity the same grid's velocity as a NRRD volume of 3-vectors (velocity_NNNNNN.nrrd), the
           density's companion (NRRD holds one field a file);
  vdb      the same grid as an OpenVDB `density` fog volume and a `velocity` vector grid
           (fluidcore.vdb), what Blender and Houdini load as smoke and use for motion blur;
           a job publishes it for every frame, a sequence.

The velocity is the air's (the run's `SavedAir`, sampled at the voxel centres) when the run
simulates the air; otherwise the particles' own velocities, mass-weighted over the same Poly6
kernels as the density (zero where there is no smoke): in a run without the air grid the model's
air is still, and zeros would blur nothing, while the particles' velocity is how the smoke moves.

One frame goes to a file of the caller's choosing (`export_frame`); a range of frames to
numbered files in a folder (`export_sequence`: smoke_000012.vdb, ..., names from
`export_name`), at most MAX_SEQUENCE_FRAMES of them; or to one zip, a bundle (`export_bundle`:
the numbered files and a `bundle.json` saying what they hold), which is what a job offers for
download. The grid formats take a voxel size (`voxel_size`, world units, at most the kernel
radius h); a bundle's default, h/4, is finer than the particles' own spacing (h/2).

Density follows the simulator (fluidcore.physics): each particle carries mass (h/2)^3 (world
units^3 of unit density, 1 = 8 particles per h^3) spread over the voxels within the kernel
radius h with Poly6 weights normalised per particle, so no mass is lost to the discretisation.
torch-free, so the worker can export without the simulator.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from fluidcore.errors import InputError
from fluidcore.files import atomic_output
from fluidcore.runs import FrameState, Run, RunRecord
from fluidcore.spec.jobs import BUNDLE_FORMATS
from fluidcore.vdb import max_file_bytes, write_vdb

SH_C0 = 0.28209479177387814  # the degree-0 spherical harmonic, Y_0^0 = 1 / (2 sqrt(pi))
MAX_VOXELS = 256**3  # a density grid larger than this (64 MiB of float32) is refused
DENSITY_SPACING = 0.5  # default voxel size, in kernel radii h
PARTICLE_CHUNK = 4096  # particles splatted at once: x 6^3 stencil voxels (spacing h/2) x 8 B = 7 MiB an array
MAX_SEQUENCE_FRAMES = 600  # 20 s at 30 fps; a ScalarFlow-preset run measured 50 ms and 32 kB a VDB frame
# A bundle's default voxel, in kernel radii h: finer than the particles' spacing (h/2), so the
# smoke's edges are not blockier than its particles. 3,000 particles in a 1 x 1.5 x 1 box at
# h = 0.04 (one core): h/2 is 55x80x55 voxels, 0.08 s to splat, 0.03 s to write as VDB, 0.5 MB;
# h/4 is 109x159x109, 0.37 s, 0.15 s, 3.8 MB a frame.
BUNDLE_SPACING = 0.25
# The most a bundle may declare (`BundlePlan.bytes`): 600 frames of that box at h/4, 2 M voxels of
# density and velocity (16 B) a frame. Its files' sizes are bounded before anything is written
# (`frame_bytes`); before issue 49 the cap counted voxels, whatever a voxel cost in the format.
MAX_BUNDLE_BYTES = 20 * 1024**3
DENSITY_VOXEL_BYTES = 16  # a density npz's float32 density and velocity (3) per voxel
PLY_VERTEX_BYTES = 68  # 17 float32 columns a Gaussian (`splat_vertices`)
# A state file holds at least 12 float32 of each Gaussian (runs.GAUSSIAN_FIELDS: means 3, log
# scales 3, quaternion 4, opacity 1, colour 1 or 3), so a frame has at most its state's bytes / 48.
STATE_GAUSSIAN_BYTES = 48
FILE_SLACK = 4096  # a file's own header (npz directory 1.9 kB, ply header, VDB's in max_file_bytes) and zip entry
BUNDLE_MANIFEST = "bundle.json"
BUNDLE_NAME = re.compile(r"(?P<fmt>[a-z]+)_f(?P<start>\d{6,})-(?P<end>\d{6,})(?:_v(?P<voxel>[0-9.e+-]+))?\.zip")


class ExportError(InputError):
    """The frame cannot be exported as asked; the message names the option."""


VELOCITY_SOURCES = ("air", "particles")  # where a grid's velocity comes from (module docstring)


@dataclass(frozen=True)
class DensityGrid:
    """Density (X, Y, Z) float32 indexed [x, y, z]; voxel [i, j, k] is centred at
    origin + (i, j, k) * spacing (world units). `velocity` (X, Y, Z, 3) float32, world units/s, on
    the same voxels when asked for, with `velocity_source` one of VELOCITY_SOURCES."""

    density: np.ndarray
    origin: np.ndarray
    spacing: float
    particle_mass: float
    velocity: np.ndarray | None = None
    velocity_source: str | None = None

    def total_mass(self) -> float:
        return float(self.density.sum(dtype=np.float64) * self.spacing**3)

    def voxel_centres(self) -> np.ndarray:
        """World positions (X * Y * Z, 3) of the voxel centres, in the grid's memory order."""
        axes = [self.origin[a] + self.spacing * np.arange(n) for a, n in enumerate(self.density.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def density_grid(positions: np.ndarray, h: float, lo: np.ndarray, hi: np.ndarray, spacing: float,
                 velocities: np.ndarray | None = None) -> DensityGrid:
    """Splat particles (N, 3) (world units) with kernel radius `h` onto a grid covering the box
    [lo, hi] plus h on every side (a particle at the box wall keeps its whole kernel). With
    `velocities` (N, 3) the grid's velocity is theirs, averaged with the same weights as the mass
    (momentum / density; zero where no particle reaches)."""
    shape = np.asarray(grid_shape(h, lo, hi, spacing))
    origin = np.asarray(lo, dtype=np.float64) - h
    mass = (h / 2) ** 3
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    reach = np.arange(-int(np.ceil(h / spacing)), int(np.ceil(h / spacing)) + 2)  # voxels a kernel can touch
    grid = np.zeros(voxel_count(tuple(shape)))
    momentum = None if velocities is None else np.zeros((voxel_count(tuple(shape)), 3))
    for first in range(0, len(points), PARTICLE_CHUNK):
        chunk = points[first : first + PARTICLE_CHUNK]
        cells = np.floor((chunk - origin) / spacing).astype(int)[:, :, None] + reach  # (n, 3, reach) per axis
        offsets = origin[:, None] + cells * spacing - chunk[:, :, None]  # voxel centre - particle, per axis
        inside = (cells >= 0) & (cells < shape[:, None])
        # The stencil is the outer product of the three axes: (n, reach, reach, reach).
        r2 = offsets[:, 0, :, None, None] ** 2 + offsets[:, 1, None, :, None] ** 2 + offsets[:, 2, None, None, :] ** 2
        within = inside[:, 0, :, None, None] & inside[:, 1, None, :, None] & inside[:, 2, None, None, :] & (r2 < h * h)
        weights = np.where(within, (h * h - np.minimum(r2, h * h)) ** 3, 0.0)  # Poly6, unnormalised
        total = weights.sum(axis=(1, 2, 3), keepdims=True)  # > 0 for a particle in the box: a voxel centre lies within h
        total[total == 0] = 1.0  # a particle beyond the grid touches no voxel and deposits nothing
        flat = (cells[:, 0, :, None, None] * shape[1] + cells[:, 1, None, :, None]) * shape[2] + cells[:, 2, None, None, :]
        share = (weights / total * (mass / spacing**3))[within]
        np.add.at(grid, flat[within], share)
        if momentum is not None:
            owner = np.broadcast_to(np.arange(len(chunk))[:, None, None, None], within.shape)[within]
            np.add.at(momentum, flat[within], share[:, None] * velocities[first + owner])
    velocity = None
    if momentum is not None:
        velocity = np.where(grid[:, None] > 0, momentum / np.where(grid > 0, grid, 1.0)[:, None], 0.0)
        velocity = velocity.reshape(*shape, 3).astype(np.float32)
    return DensityGrid(grid.reshape(shape).astype(np.float32), origin, float(spacing), mass, velocity,
                       None if velocity is None else "particles")


def _shape(h: float, lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[int, int, int]:
    """Voxels per axis, in Python ints: numpy's int64 product of a 1e-9 voxel's shape overflowed to
    a negative count that passed the cap (issue 49); an extent over the spacing that is not a
    finite number is refused here."""
    with np.errstate(over="ignore", divide="ignore"):
        extent = (np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64) + 2 * h) / spacing
    if not np.all(np.isfinite(extent)):
        raise ExportError(f"voxel size {spacing:g}: the box over it is not a finite number of voxels")
    return tuple(math.ceil(float(n)) + 1 for n in extent)  # type: ignore[return-value]


def voxel_count(shape: tuple[int, ...]) -> int:
    """Voxels of a grid, as an exact Python int (never numpy's int64, which wraps)."""
    return math.prod(shape)


def shape_text(shape: tuple[int, ...]) -> str:
    """A grid's shape for a message: 55x80x55, or 1.08e+300x... for a voxel size far too small."""
    return "x".join(str(n) if n < 10**7 else f"{n:.3g}" for n in shape)


def _smallest_fitting(h: float, lo: np.ndarray, hi: np.ndarray, too_small: float) -> float:
    """The smallest voxel size whose grid holds at most MAX_VOXELS, rounded up to 3 digits:
    bisection, the voxel count falling as the size grows."""
    fits = 2 * too_small
    while voxel_count(_shape(h, lo, hi, fits)) > MAX_VOXELS:
        fits *= 2
    for _ in range(40):
        middle = (too_small + fits) / 2
        too_small, fits = (too_small, middle) if voxel_count(_shape(h, lo, hi, middle)) <= MAX_VOXELS else (middle, fits)
    scale = 10.0 ** (2 - int(np.floor(np.log10(fits))))
    return float(np.ceil(fits * scale) / scale)


def grid_shape(h: float, lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[int, int, int]:
    """The voxels of the grid `density_grid` splats the box [lo, hi] onto at `spacing` (world
    units); an ExportError naming the option when the spacing is not in (0, h] or the grid would
    hold more than MAX_VOXELS, with the smallest voxel size that fits this box."""
    if not 0 < spacing <= h:
        raise ExportError(f"voxel size must be in (0, {h:g}] world units (the kernel radius h), got {spacing:g}")
    shape = _shape(h, lo, hi, spacing)
    if voxel_count(shape) <= MAX_VOXELS:
        return shape
    fits = _smallest_fitting(h, lo, hi, spacing)
    hint = f"the smallest that fits this box is {fits:g}" if fits <= h else "even the kernel radius does not fit this box"
    raise ExportError(f"voxel size {spacing:g}: a {shape_text(shape)} grid exceeds {MAX_VOXELS} voxels (256^3); {hint}")


def frame_density(run: Run, state: FrameState, spacing: float | None = None) -> DensityGrid:
    """The density grid of a run's frame, over its scene box, with the scene's kernel radius, and
    its velocity: the air's where the frame holds the air, else the particles' (module docstring)."""
    h = run.scene.physics.h
    alive = state.alive.astype(bool)
    positions = state.positions[alive]
    lo, hi = np.asarray(run.scene.box_lo), np.asarray(run.scene.box_hi)
    if state.air is None:
        return density_grid(positions, h, lo, hi, spacing or DENSITY_SPACING * h, state.velocities[alive])
    grid = density_grid(positions, h, lo, hi, spacing or DENSITY_SPACING * h)
    velocity = state.air.velocity_at(grid.voxel_centres()).reshape(*grid.density.shape, 3)
    return replace(grid, velocity=velocity, velocity_source="air")



def splat_vertices(gaussians: dict[str, np.ndarray]) -> np.ndarray:
    """A structured array in the 3D Gaussian splatting PLY layout (colour as the SH DC term)."""
    means = gaussians["means"]
    colors = gaussians["colors"]
    colors = np.repeat(colors, 3, axis=1) if colors.shape[1] == 1 else colors
    quats = gaussians["quats"] / np.linalg.norm(gaussians["quats"], axis=1, keepdims=True)
    columns = {
        **{axis: means[:, i] for i, axis in enumerate("xyz")},
        **{f"n{axis}": np.zeros(len(means)) for axis in "xyz"},
        **{f"f_dc_{i}": (colors[:, i] - 0.5) / SH_C0 for i in range(3)},
        "opacity": gaussians["opacity_logits"],
        **{f"scale_{i}": gaussians["log_scales"][:, i] for i in range(3)},
        **{f"rot_{i}": quats[:, i] for i in range(4)},  # w, x, y, z, as the reference layout
    }
    vertices = np.empty(len(means), dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        vertices[name] = values
    return vertices


@dataclass
class ExportFrame:
    """One frame of a run as the writers read it. Its density grid (with the velocity) is splatted
    once, when a first format asks, and shared by the others: a job's last frame goes out as
    density npz, density and velocity NRRD and VDB from one grid (0.08 s each on dev scene F's
    55 x 80 x 55 grid)."""

    run: Run
    state: FrameState
    spacing: float | None = None  # the grid's voxel size; None: DENSITY_SPACING x h

    @cached_property
    def grid(self) -> DensityGrid:
        return frame_density(self.run, self.state, self.spacing)


def _write_npz(frame: ExportFrame, path: Path) -> None:
    with path.open("wb") as file:
        np.savez(file, **frame.state.export())


def _write_ply(frame: ExportFrame, path: Path) -> None:
    from plyfile import PlyData, PlyElement

    PlyData([PlyElement.describe(splat_vertices(frame.state.gaussians), "vertex")]).write(str(path))


def _write_density(frame: ExportFrame, path: Path) -> None:
    grid = frame.grid
    with path.open("wb") as file:
        np.savez(
            file, density=grid.density, origin=grid.origin, spacing=np.asarray(grid.spacing),
            particle_mass=np.asarray(grid.particle_mass), rest_density=np.asarray(frame.run.scene.physics.rho0),
            velocity=grid.velocity, velocity_source=np.asarray(grid.velocity_source),
        )


def _nrrd(grid: DensityGrid, values: np.ndarray, path: Path) -> None:
    """`values` on `grid`'s voxels, (X, Y, Z) or (X, Y, Z, 3), as NRRD 4: raw little-endian float32,
    x fastest (a vector's components fastest of all), origin and spacing in the header."""
    s = grid.spacing
    vector = values.ndim == 4
    header = "\n".join(
        [
            "NRRD0004",
            "type: float",
            f"dimension: {values.ndim}",
            f"sizes: {' '.join(map(str, (3, *values.shape[:3]) if vector else values.shape))}",
            "space dimension: 3",
            f"space directions: {'none ' if vector else ''}({s!r},0,0) (0,{s!r},0) (0,0,{s!r})",
            f"space origin: ({','.join(repr(float(v)) for v in grid.origin)})",
            f"kinds: {'3-vector ' if vector else ''}domain domain domain",
            "endian: little",
            "encoding: raw",
            "",
            "",
        ]
    )
    data = np.moveaxis(values, 3, 0) if vector else values
    with path.open("wb") as file:
        file.write(header.encode("ascii"))
        file.write(data.astype("<f4").tobytes(order="F"))  # NRRD: the first axis varies fastest


def _write_nrrd(frame: ExportFrame, path: Path) -> None:
    grid = frame.grid
    _nrrd(grid, grid.density, path)


def _write_velocity(frame: ExportFrame, path: Path) -> None:
    grid = frame.grid
    _nrrd(grid, grid.velocity, path)


def _write_vdb(frame: ExportFrame, path: Path) -> None:
    grid = frame.grid
    # velocity active where there is smoke: what motion blur reads, and a sequence of dense air
    # grids would cost 12 bytes a voxel of the whole box in every frame
    velocity = np.where(grid.density[..., None] > 0, grid.velocity, 0.0)
    write_vdb(path, {"density": grid.density, "velocity": velocity}, grid.origin, grid.spacing)


@dataclass(frozen=True)
class Exporter:
    suffix: str
    write: Callable[[ExportFrame, Path], None]
    media_type: str
    stem: str  # what the file holds, the start of its numbered name (export_name)
    every_frame: bool = False  # a job publishes every frame (a sequence), not only the last
    gridded: bool = False  # written from the density grid: takes a voxel size


EXPORTERS: dict[str, Exporter] = {
    "npz": Exporter(".npz", _write_npz, "application/octet-stream", "state"),
    "ply": Exporter(".ply", _write_ply, "application/octet-stream", "splats"),
    "density": Exporter(".npz", _write_density, "application/octet-stream", "density", gridded=True),
    "nrrd": Exporter(".nrrd", _write_nrrd, "application/octet-stream", "density", gridded=True),
    "velocity": Exporter(".nrrd", _write_velocity, "application/octet-stream", "velocity", gridded=True),
    "vdb": Exporter(".vdb", _write_vdb, "application/octet-stream", "smoke", every_frame=True, gridded=True),
}


def _check_format(fmt: str, voxel_size: float | None, formats: tuple[str, ...] = tuple(EXPORTERS)) -> None:
    if fmt not in formats:
        raise ExportError(f"format must be one of {', '.join(formats)}, got {fmt!r}")
    if voxel_size is not None and not EXPORTERS[fmt].gridded:
        gridded = ", ".join(name for name in formats if EXPORTERS[name].gridded)
        raise ExportError(f"voxel size: {fmt} holds particles, not a grid; a voxel size applies to {gridded}")


def _open(run_dir: str | os.PathLike[str], fmt: str, voxel_size: float | None = None) -> Run:
    _check_format(fmt, voxel_size)
    run = Run.open(run_dir)
    if voxel_size is not None:
        grid_shape(run.scene.physics.h, np.asarray(run.scene.box_lo), np.asarray(run.scene.box_hi), voxel_size)
    return run


def _held(run: RunRecord, label: str) -> str:
    frames = run.frames()
    return f"{label} (frames {f'{frames[0]}..{frames[-1]}' if frames else 'none yet'})"


def _check_frames(run: RunRecord, frames: tuple[int, int], label: str) -> None:
    """[start, end) is a range of at most MAX_SEQUENCE_FRAMES finished frames of the run."""
    start, end = frames
    if not 0 <= start < end:
        raise ExportError(f"frames must satisfy 0 <= START < END, got {start}:{end}")
    if end - start > MAX_SEQUENCE_FRAMES:
        raise ExportError(f"frames {start}:{end} is {end - start} frames; a sequence holds at most {MAX_SEQUENCE_FRAMES}")
    missing = sorted(set(range(start, end)) - set(run.frames()))
    if missing:
        raise ExportError(f"frames {start}:{end}: frame {missing[0]} is not a finished frame of {_held(run, label)}")


def _write(frame: ExportFrame, fmt: str, out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out, suffix=EXPORTERS[fmt].suffix) as temporary:
        EXPORTERS[fmt].write(frame, temporary)
    return out


def last_frame(run_dir: str | os.PathLike[str]) -> int:
    """The run's last finished frame (what `fluidnexus export` writes unless told a frame)."""
    frames = Run.open(run_dir).frames()
    if not frames:
        raise ExportError(f"run: {run_dir} has no finished frames to export")
    return frames[-1]


def export_frame(run_dir: str | os.PathLike[str], frame: int, fmt: str, out: str | os.PathLike[str],
                 voxel_size: float | None = None) -> Path:
    """Write `frame` of the run in `run_dir` as `fmt` (a key of EXPORTERS) to `out`, atomically;
    a grid format at `voxel_size` (world units; default DENSITY_SPACING x h)."""
    run = _open(run_dir, fmt, voxel_size)
    if frame not in run.frames():
        raise ExportError(f"frame {frame} is not a finished frame of {_held(run, str(run_dir))}")
    return _write(ExportFrame(run, run.read_frame(frame), voxel_size), fmt, Path(out))


def export_name(frame: int, fmt: str) -> str:
    """The file name of a frame's export, numbered for sequences: smoke_000123.vdb,
    splats_000123.ply, density_000123.npz, ..."""
    return f"{EXPORTERS[fmt].stem}_{frame:06d}{EXPORTERS[fmt].suffix}"


def export_sequence(
    run_dir: str | os.PathLike[str], frames: tuple[int, int], fmt: str, out_dir: str | os.PathLike[str],
    voxel_size: float | None = None,
) -> list[Path]:
    """Write the frames [start, end) of the run as `fmt` into `out_dir`, one numbered file each
    (export_name), a grid format at `voxel_size`. Every frame of the range must be finished; at
    most MAX_SEQUENCE_FRAMES."""
    run = _open(run_dir, fmt, voxel_size)
    _check_frames(run, frames, str(run_dir))
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ExportError(f"out: {out_dir} is a file; a sequence goes into a folder")
    return [_write(ExportFrame(run, run.read_frame(t), voxel_size), fmt, Path(out_dir) / export_name(t, fmt))
            for t in range(*frames)]


OnFrame = Callable[[int, int], None]  # (frames written, frames in all): a bundle's progress


@dataclass(frozen=True)
class BundlePlan:
    """A bundle checked against its run, before anything is written: the format, the frames
    [start, end), and the voxel size (world units; None for ply) with its grid's shape."""

    fmt: str
    frames: tuple[int, int]
    voxel_size: float | None
    shape: tuple[int, int, int] | None
    bytes: int | None = None  # the most its zip can take (`frame_bytes` over the frames); None: not planned

    @property
    def name(self) -> str:
        """The zip's file name, which says what it holds: vdb_f000000-000030_v0.01.zip (frames
        [0, 30), voxel 0.01); the service stores a bundle under it, so asking again finds it."""
        voxel = "" if self.voxel_size is None else f"_v{self.voxel_size:.4g}"
        return f"{self.fmt}_f{self.frames[0]:06d}-{self.frames[1]:06d}{voxel}.zip"

    @classmethod
    def from_name(cls, name: str) -> BundlePlan:
        """The plan a bundle's file name states (`name`'s inverse; the grid's shape is not in it)."""
        found = BUNDLE_NAME.fullmatch(name)
        if found is None or found["fmt"] not in BUNDLE_FORMATS:
            raise ExportError(f"{name!r} is not a bundle's name")
        voxel = None if found["voxel"] is None else float(found["voxel"])
        return cls(found["fmt"], (int(found["start"]), int(found["end"])), voxel, None)


def default_frames(run: RunRecord) -> tuple[int, int]:
    """A bundle's frames when none are asked for: the run's, the last MAX_SEQUENCE_FRAMES of them."""
    done = run.frames()
    if not done:
        raise ExportError("the run has no finished frames to export")
    return max(done[0], done[-1] + 1 - MAX_SEQUENCE_FRAMES), done[-1] + 1


def bundle_voxel_size(h: float, asked: float | None = None) -> float:
    """A bundle's voxel size: `asked`, or BUNDLE_SPACING x h, to the 4 digits its name states."""
    return float(f"{BUNDLE_SPACING * h if asked is None else asked:.4g}")


def frame_bytes(fmt: str, shape: tuple[int, int, int] | None, state_bytes: int) -> int:
    """The most bytes one frame of a bundle of `fmt` can take in its zip: a grid of `shape`, or
    for ply the Gaussians a state file of `state_bytes` can hold. Upper bounds that hold for any
    smoke (every voxel filled), so a bundle is refused before work, never cut short."""
    if fmt == "ply":
        return -(-state_bytes // STATE_GAUSSIAN_BYTES) * PLY_VERTEX_BYTES + FILE_SLACK
    assert shape is not None, "a grid format has a shape"
    if fmt == "vdb":
        return max_file_bytes(shape, {"density": 4, "velocity": 12}) + FILE_SLACK
    return voxel_count(shape) * DENSITY_VOXEL_BYTES + FILE_SLACK


def plan_bundle(run: RunRecord, fmt: str, frames: tuple[int, int] | None = None, voxel_size: float | None = None,
                label: str = "the run", state_bytes: Mapping[int, int] | None = None) -> BundlePlan:
    """Check a bundle against the run's manifest (torch-free and reading no frame, so the API
    refuses a bad request before queueing it): a format of BUNDLE_FORMATS, finished frames, a
    voxel size for the grid formats (`bundle_voxel_size`) whose grid fits MAX_VOXELS a frame, and
    at most MAX_BUNDLE_BYTES declared over the frames (`frame_bytes`). A ply bundle's size needs
    the frames' state file sizes: `state_bytes` by frame (the API lists them in storage), read
    from the run folder when `run` is one."""
    _check_format(fmt, voxel_size, BUNDLE_FORMATS)
    frames = default_frames(run) if frames is None else (int(frames[0]), int(frames[1]))
    _check_frames(run, frames, label)
    spacing = shape = None
    if EXPORTERS[fmt].gridded:
        h = run.scene.physics.h
        spacing = bundle_voxel_size(h, voxel_size)
        shape = grid_shape(h, np.asarray(run.scene.box_lo), np.asarray(run.scene.box_hi), spacing)
    sizes = _state_sizes(run, frames, state_bytes, label) if fmt == "ply" else {}
    declared = BUNDLE_SLACK + sum(frame_bytes(fmt, shape, sizes.get(t, 0)) for t in range(*frames))
    if declared > MAX_BUNDLE_BYTES:
        grid = "" if shape is None else f" of {shape_text(shape)} voxels"
        raise ExportError(f"{frames[1] - frames[0]} frames{grid} as {fmt} may take {declared / 1024**3:.3g} GiB, more "
                          f"than a bundle's {MAX_BUNDLE_BYTES / 1024**3:.3g} GiB; choose fewer frames"
                          f"{' or a larger voxel size' if shape is not None else ''}")
    return BundlePlan(fmt, frames, spacing, shape, declared)


BUNDLE_SLACK = 64 * 1024  # BUNDLE_MANIFEST (its list of up to 600 file names) and the zip's directory end


def _state_sizes(run: RunRecord, frames: tuple[int, int], given: Mapping[int, int] | None, label: str) -> Mapping[int, int]:
    """The frames' state file sizes: `given`, else read from the run folder."""
    if given is None:
        if not isinstance(run, Run):
            raise TypeError("a ply bundle of a run record needs its state file sizes")
        return {t: run.state_path(t).stat().st_size for t in range(*frames)}
    missing = [t for t in range(*frames) if t not in given]
    if missing:
        raise ExportError(f"frames {frames[0]}:{frames[1]}: frame {missing[0]}'s state is missing from {label}")
    return given


def export_bundle(run_dir: str | os.PathLike[str], plan: BundlePlan, out: str | os.PathLike[str],
                  on_frame: OnFrame | None = None) -> Path:
    """Write the plan's frames as one zip at `out` (atomically): the numbered files (export_name)
    and BUNDLE_MANIFEST (format, frames, fps, voxel size, up, kernel radius, files). Stored, not
    deflated: VDB and PLY barely compress, and storing keeps memory to one frame at a time."""
    run = Run.open(run_dir)
    plan = plan_bundle(run, plan.fmt, plan.frames, plan.voxel_size, str(run_dir))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    names = [export_name(t, plan.fmt) for t in range(*plan.frames)]
    written = 0
    with (atomic_output(out, suffix=".zip") as temporary, tempfile.TemporaryDirectory(dir=out.parent) as scratch,
          zipfile.ZipFile(temporary, "w", zipfile.ZIP_STORED) as bundle):
        for done, (t, name) in enumerate(zip(range(*plan.frames), names, strict=True), start=1):
            file = _write(ExportFrame(run, run.read_frame(t), plan.voxel_size), plan.fmt, Path(scratch) / name)
            written += file.stat().st_size
            if written > (plan.bytes or 0):  # the declared bound is what the owner's quota reserved: never past it
                raise RuntimeError(f"bundle {plan.name}: {written} bytes by frame {t}, past the {plan.bytes} it declared")
            bundle.write(file, name)
            file.unlink()
            if on_frame is not None:
                on_frame(done, len(names))
        scene = run.scene
        about = {"format": plan.fmt, "frames": list(plan.frames), "fps": run.fps, "voxel_size": plan.voxel_size,
                 "grid_shape": None if plan.shape is None else list(plan.shape), "up": list(scene.up),
                 "kernel_radius": scene.physics.h, "files": names}
        bundle.writestr(BUNDLE_MANIFEST, json.dumps(about, indent=1))
    return out


def export_artifacts(run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> list[Path]:
    """What a finished job publishes next to its videos, into `out_dir`: the run's last frame in
    every registered format, and every frame (the last MAX_SEQUENCE_FRAMES) in the formats that
    VFX tools import as sequences (`every_frame`); other frames are one `fluidnexus export` away.
    Each frame is read once and its formats share its density grid (`ExportFrame`)."""
    last = last_frame(run_dir)
    run = Run.open(run_dir)
    first = max(run.frames()[0], last + 1 - MAX_SEQUENCE_FRAMES)
    written = []
    for t in range(first, last + 1):
        frame = ExportFrame(run, run.read_frame(t))
        for fmt, exporter in EXPORTERS.items():
            if exporter.every_frame or t == last:
                written.append(_write(frame, fmt, Path(out_dir) / export_name(t, fmt)))
    return written
