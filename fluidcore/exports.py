"""Exporters: one frame of a run, written in a format other tools read (docs/exports.md).

`EXPORTERS` is the one registry, keyed by the format name the CLI (`fluidnexus export
--format`) and the API's artifacts use; adding a format is one entry here.

  npz      the frame's arrays: live physical particles (world units, units/s) and the visual
           Gaussians, as `numpy.savez` (what `fluidnexus export` always wrote);
  ply      the visual Gaussians in the 3D Gaussian splatting PLY layout that splat viewers and
           VFX plug-ins read (x y z, nx ny nz, f_dc_0..2, opacity, scale_0..2, rot_0..3);
  density  the physical density on a voxel grid in world units, as .npz (density, origin,
           spacing), mass conserving: density x voxel volume sums to the particles' mass;
  nrrd     the same grid as a NRRD volume (raw float32, origin and spacing in the header),
           which ParaView, 3D Slicer and Houdini's NRRD readers open.

Density follows the simulator (fluidcore.physics): each particle carries mass (h/2)^3 (world
units^3 of unit density, 1 = 8 particles per h^3) spread over the voxels within the kernel
radius h with Poly6 weights normalised per particle, so no mass is lost to the discretisation.
torch-free, so the worker can export without the simulator.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fluidcore.files import atomic_output
from fluidcore.runs import FrameState, Run

SH_C0 = 0.28209479177387814  # the degree-0 spherical harmonic, Y_0^0 = 1 / (2 sqrt(pi))
MAX_VOXELS = 256**3  # a density grid larger than this (64 MiB of float32) is refused
DENSITY_SPACING = 0.5  # default voxel size, in kernel radii h


class ExportError(ValueError):
    """The frame cannot be exported as asked; the message names the option."""


@dataclass(frozen=True)
class DensityGrid:
    """Density (X, Y, Z) float32 indexed [x, y, z]; voxel [i, j, k] is centred at
    origin + (i, j, k) * spacing (world units)."""

    density: np.ndarray
    origin: np.ndarray
    spacing: float
    particle_mass: float

    def total_mass(self) -> float:
        return float(self.density.sum(dtype=np.float64) * self.spacing**3)


def density_grid(positions: np.ndarray, h: float, lo: np.ndarray, hi: np.ndarray, spacing: float) -> DensityGrid:
    """Splat particles (N, 3) (world units) with kernel radius `h` onto a grid covering the box
    [lo, hi] plus h on every side (a particle at the box wall keeps its whole kernel)."""
    if not 0 < spacing <= h:
        raise ExportError(f"spacing must be in (0, h = {h:g}] world units, got {spacing:g}")
    origin = np.asarray(lo, dtype=np.float64) - h
    shape = np.ceil((np.asarray(hi, dtype=np.float64) + h - origin) / spacing).astype(int) + 1
    if int(np.prod(shape)) > MAX_VOXELS:
        raise ExportError(f"a {'x'.join(map(str, shape))} density grid exceeds {MAX_VOXELS} voxels; choose a larger spacing")
    mass = (h / 2) ** 3
    points = np.asarray(positions, dtype=np.float64)
    base = np.floor((points - origin) / spacing).astype(int)
    reach = range(-int(np.ceil(h / spacing)), int(np.ceil(h / spacing)) + 2)
    stencil = [np.array((i, j, k)) for i in reach for j in reach for k in reach]

    def poly6(offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cells = base + offset
        r2 = np.sum((origin + cells * spacing - points) ** 2, axis=1)
        inside = np.all((cells >= 0) & (cells < shape), axis=1)
        return cells, np.where(inside & (r2 < h * h), (h * h - r2) ** 3, 0.0)

    # Two passes over the stencil (normalise, then deposit) keep memory at O(particles).
    total = sum(poly6(offset)[1] for offset in stencil)  # > 0: a voxel centre lies within h of any point
    grid = np.zeros(shape)
    for offset in stencil:
        cells, weights = poly6(offset)
        hit = weights > 0
        np.add.at(grid, tuple(cells[hit].T), weights[hit] / total[hit] * mass / spacing**3)
    return DensityGrid(grid.astype(np.float32), origin, float(spacing), mass)


def frame_density(run: Run, state: FrameState, spacing: float | None = None) -> DensityGrid:
    """The density grid of a run's frame, over its scene box, with the scene's kernel radius."""
    h = run.scene.physics.h
    positions = state.positions[state.alive.astype(bool)]
    return density_grid(positions, h, np.asarray(run.scene.box_lo), np.asarray(run.scene.box_hi), spacing or DENSITY_SPACING * h)


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


def _write_npz(run: Run, state: FrameState, path: Path) -> None:
    with path.open("wb") as file:
        np.savez(file, **state.export())


def _write_ply(run: Run, state: FrameState, path: Path) -> None:
    from plyfile import PlyData, PlyElement

    PlyData([PlyElement.describe(splat_vertices(state.gaussians), "vertex")]).write(str(path))


def _write_density(run: Run, state: FrameState, path: Path) -> None:
    grid = frame_density(run, state)
    with path.open("wb") as file:
        np.savez(
            file, density=grid.density, origin=grid.origin, spacing=np.asarray(grid.spacing),
            particle_mass=np.asarray(grid.particle_mass), rest_density=np.asarray(run.scene.physics.rho0),
        )


def _write_nrrd(run: Run, state: FrameState, path: Path) -> None:
    grid = frame_density(run, state)
    s = grid.spacing
    header = "\n".join(
        [
            "NRRD0004",
            "type: float",
            "dimension: 3",
            f"sizes: {' '.join(map(str, grid.density.shape))}",
            "space dimension: 3",
            f"space directions: ({s!r},0,0) (0,{s!r},0) (0,0,{s!r})",
            f"space origin: ({','.join(repr(float(v)) for v in grid.origin)})",
            "kinds: domain domain domain",
            "endian: little",
            "encoding: raw",
            "",
            "",
        ]
    )
    with path.open("wb") as file:
        file.write(header.encode("ascii"))
        file.write(grid.density.astype("<f4").tobytes(order="F"))  # NRRD: the first axis (x) varies fastest


@dataclass(frozen=True)
class Exporter:
    suffix: str
    write: Callable[[Run, FrameState, Path], None]
    media_type: str


EXPORTERS: dict[str, Exporter] = {
    "npz": Exporter(".npz", _write_npz, "application/octet-stream"),
    "ply": Exporter(".ply", _write_ply, "application/octet-stream"),
    "density": Exporter(".npz", _write_density, "application/octet-stream"),
    "nrrd": Exporter(".nrrd", _write_nrrd, "application/octet-stream"),
}


def export_frame(run_dir: str | os.PathLike[str], frame: int, fmt: str, out: str | os.PathLike[str]) -> Path:
    """Write `frame` of the run in `run_dir` as `fmt` (a key of EXPORTERS) to `out`, atomically."""
    if fmt not in EXPORTERS:
        raise ExportError(f"format must be one of {', '.join(EXPORTERS)}, got {fmt!r}")
    run = Run.open(run_dir)
    if frame not in run.frames():
        frames = run.frames()
        held = f"{frames[0]}..{frames[-1]}" if frames else "none yet"
        raise ExportError(f"frame {frame} is not a finished frame of {run_dir} (frames {held})")
    state = run.read_frame(frame)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out, suffix=EXPORTERS[fmt].suffix) as temporary:
        EXPORTERS[fmt].write(run, state, temporary)
    return out


def export_name(frame: int, fmt: str) -> str:
    """The file name of a frame's export: frame_000123.ply, frame_000123.density.npz, ..."""
    suffix = EXPORTERS[fmt].suffix
    return f"frame_{frame:06d}{suffix}" if suffix.lstrip(".") == fmt else f"frame_{frame:06d}.{fmt}{suffix}"


def export_artifacts(run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> list[Path]:
    """The run's last frame in every registered format, into `out_dir` (what a finished job
    publishes next to its videos; other frames are one `fluidnexus export` away)."""
    frames = Run.open(run_dir).frames()
    if not frames:
        raise ExportError(f"run: {run_dir} has no finished frames to export")
    return [export_frame(run_dir, frames[-1], fmt, Path(out_dir) / export_name(frames[-1], fmt)) for fmt in EXPORTERS]
