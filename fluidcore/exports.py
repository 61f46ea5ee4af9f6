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
`export_name`), at most MAX_SEQUENCE_FRAMES of them.

Density follows the simulator (fluidcore.physics): each particle carries mass (h/2)^3 (world
units^3 of unit density, 1 = 8 particles per h^3) spread over the voxels within the kernel
radius h with Poly6 weights normalised per particle, so no mass is lost to the discretisation.
torch-free, so the worker can export without the simulator.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from fluidcore.errors import InputError
from fluidcore.files import atomic_output
from fluidcore.runs import FrameState, Run
from fluidcore.vdb import write_vdb

SH_C0 = 0.28209479177387814  # the degree-0 spherical harmonic, Y_0^0 = 1 / (2 sqrt(pi))
MAX_VOXELS = 256**3  # a density grid larger than this (64 MiB of float32) is refused
DENSITY_SPACING = 0.5  # default voxel size, in kernel radii h
PARTICLE_CHUNK = 4096  # particles splatted at once: x 6^3 stencil voxels (spacing h/2) x 8 B = 7 MiB an array
MAX_SEQUENCE_FRAMES = 600  # 20 s at 30 fps; a ScalarFlow-preset run measured 50 ms and 32 kB a VDB frame


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
    if not 0 < spacing <= h:
        raise ExportError(f"spacing must be in (0, h = {h:g}] world units, got {spacing:g}")
    origin = np.asarray(lo, dtype=np.float64) - h
    shape = np.ceil((np.asarray(hi, dtype=np.float64) + h - origin) / spacing).astype(int) + 1
    if int(np.prod(shape)) > MAX_VOXELS:
        raise ExportError(f"a {'x'.join(map(str, shape))} density grid exceeds {MAX_VOXELS} voxels; choose a larger spacing")
    mass = (h / 2) ** 3
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    reach = np.arange(-int(np.ceil(h / spacing)), int(np.ceil(h / spacing)) + 2)  # voxels a kernel can touch
    grid = np.zeros(int(np.prod(shape)))
    momentum = None if velocities is None else np.zeros((int(np.prod(shape)), 3))
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

    @cached_property
    def grid(self) -> DensityGrid:
        return frame_density(self.run, self.state)


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


EXPORTERS: dict[str, Exporter] = {
    "npz": Exporter(".npz", _write_npz, "application/octet-stream", "state"),
    "ply": Exporter(".ply", _write_ply, "application/octet-stream", "splats"),
    "density": Exporter(".npz", _write_density, "application/octet-stream", "density"),
    "nrrd": Exporter(".nrrd", _write_nrrd, "application/octet-stream", "density"),
    "velocity": Exporter(".nrrd", _write_velocity, "application/octet-stream", "velocity"),
    "vdb": Exporter(".vdb", _write_vdb, "application/octet-stream", "smoke", every_frame=True),
}


def _open(run_dir: str | os.PathLike[str], fmt: str) -> Run:
    if fmt not in EXPORTERS:
        raise ExportError(f"format must be one of {', '.join(EXPORTERS)}, got {fmt!r}")
    return Run.open(run_dir)


def _held(run: Run, run_dir: str | os.PathLike[str]) -> str:
    frames = run.frames()
    return f"{run_dir} (frames {f'{frames[0]}..{frames[-1]}' if frames else 'none yet'})"


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


def export_frame(run_dir: str | os.PathLike[str], frame: int, fmt: str, out: str | os.PathLike[str]) -> Path:
    """Write `frame` of the run in `run_dir` as `fmt` (a key of EXPORTERS) to `out`, atomically."""
    run = _open(run_dir, fmt)
    if frame not in run.frames():
        raise ExportError(f"frame {frame} is not a finished frame of {_held(run, run_dir)}")
    return _write(ExportFrame(run, run.read_frame(frame)), fmt, Path(out))


def export_name(frame: int, fmt: str) -> str:
    """The file name of a frame's export, numbered for sequences: smoke_000123.vdb,
    splats_000123.ply, density_000123.npz, ..."""
    return f"{EXPORTERS[fmt].stem}_{frame:06d}{EXPORTERS[fmt].suffix}"


def export_sequence(
    run_dir: str | os.PathLike[str], frames: tuple[int, int], fmt: str, out_dir: str | os.PathLike[str]
) -> list[Path]:
    """Write the frames [start, end) of the run as `fmt` into `out_dir`, one numbered file each
    (export_name). Every frame of the range must be finished; at most MAX_SEQUENCE_FRAMES."""
    start, end = frames
    if not 0 <= start < end:
        raise ExportError(f"frames must satisfy 0 <= START < END, got {start}:{end}")
    if end - start > MAX_SEQUENCE_FRAMES:
        raise ExportError(f"frames {start}:{end} is {end - start} frames; a sequence holds at most {MAX_SEQUENCE_FRAMES}")
    run = _open(run_dir, fmt)
    missing = sorted(set(range(start, end)) - set(run.frames()))
    if missing:
        raise ExportError(f"frames {start}:{end}: frame {missing[0]} is not a finished frame of {_held(run, run_dir)}")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ExportError(f"out: {out_dir} is a file; a sequence goes into a folder")
    return [_write(ExportFrame(run, run.read_frame(t)), fmt, Path(out_dir) / export_name(t, fmt)) for t in range(start, end)]


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
