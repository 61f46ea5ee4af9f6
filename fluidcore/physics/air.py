"""The air around the smoke: an incompressible velocity field on a coarse staggered grid.

Both motion models use it. The paper's particles (`fluidcore.physics.paper`) feel it through
their drag, f = -k (v - v_env) max(0, 1 - rho/rho0), with v_env the air's velocity at the
particle (`AirGrid.velocity_at`), and it feels them through buoyancy (`AirGrid.step`); the
buoyant-air carrier (`fluidcore.physics.carrier`) is this air, its particles markers it carries.
An air step from time t to t + dt is composed of:

  1. self-advection, semi-Lagrangian (`advect`: trace each face back along the velocity, take
     the value there);
  2. body forces (`accelerate`): an acceleration per cell the model computes from its smoke
     (buoyancy), the wind (a `ForceField` evaluated at the faces) and, optionally, vorticity
     confinement; each face velocity is then capped at the model's speed limit (drag cannot move
     a particle faster, and it keeps a runaway force finite);
  3. optionally an eddy viscosity (`diffuse`);
  4. pressure projection (`project`): the floor (the box face gravity points through) and the
     solid balls are no-through walls, the other five faces are open (pressure 0 just outside,
     air flows in and out).

`step` is the paper model's composition: buoyancy = the smoke fraction x the smoke's buoyancy
(`PBFConfig.body_acceleration`) x `buoyancy`, the smoke fraction being the particles splatted
trilinearly onto the cells at the rest density (1 = a cell full of smoke at rho0).

The grid is a MAC grid (normal velocities on cell faces) over the scene box with `cells` cells
on its longest side and cubic cells. The pressure solve is conjugate gradients preconditioned
by the exact inverse of the ball-free Laplacian, applied by fast diagonalisation (the 1-D
eigenbases of each axis, with the floor's Neumann and the open faces' Dirichlet conditions):
without a ball that is a direct solve (one iteration), and a ball costs a few more. Everything
is vectorised torch and runs on the device of the state (CPU or CUDA).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from fluidcore.physics import checks
from fluidcore.physics.forces import ForceField
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Sphere, Vec3
from fluidcore.spec.simulation import AIR_CELLS  # the one range of the grid's cells, and why it is that

MIN_CELLS_PER_AXIS = 2  # trilinear sampling and central differences need two cells on every axis
DIFFUSION_STABLE = 1.0 / 6.0  # the largest nu dt / dx^2 an explicit pass of the 7-point Laplacian takes


@dataclass
class AirState:
    """Face velocities of the air on an `AirGrid`'s MAC grid, world units / s: the x component on
    the x faces (nx+1, ny, nz), y on the y faces (nx, ny+1, nz), z on the z faces (nx, ny, nz+1).
    `origin` (the grid's lowest corner) and `spacing` (the cell size), world units, travel with
    the faces so a saved frame says where its air is without the grid that made it
    (`fluidcore.runs.SavedAir`, read torch-free by the exporter and the API)."""

    faces: tuple[Tensor, Tensor, Tensor]
    origin: tuple[float, float, float]
    spacing: float

    @property
    def device(self) -> torch.device:
        return self.faces[0].device

    def clone(self) -> AirState:
        return AirState(tuple(f.clone() for f in self.faces), self.origin, self.spacing)  # type: ignore[arg-type]

    def to(self, device: torch.device | str) -> AirState:
        return AirState(tuple(f.to(device) for f in self.faces), self.origin, self.spacing)  # type: ignore[arg-type]


@dataclass(frozen=True)
class AirStats:
    """What one projection did: solver iterations, and the largest |divergence| (1/s) over the air
    cells before and after it (after <= tolerance x before when the solver converged).
    `converged` is False when the solver stopped at max_iterations short of its tolerance: the
    air then keeps some divergence, which the simulator counts (`StepStats.air_unconverged`)."""

    iterations: int
    divergence_before: float
    divergence_after: float
    converged: bool = True


@dataclass(frozen=True)
class _Walls:
    """The no-through faces of one step: weight (1 open, 0 wall) and wall velocity per face
    component, and the cells that hold air (the pressure unknowns)."""

    weights: tuple[Tensor, Tensor, Tensor]
    velocities: tuple[Tensor, Tensor, Tensor]
    air: Tensor  # (nx, ny, nz) bool


class AirGrid:
    """Geometry and constants of the air over `box` (see the module docstring for the step).

    cells: cells on the box's longest side (the cells are cubes; the grid covers the box and
    may overhang it by less than a cell on the other axes). down: the direction of gravity;
    the box face it points through is the closed floor (the Simulator checks it against its
    config). buoyancy: multiple of the smoke's buoyancy given to a cell full of smoke.
    vorticity: confinement epsilon (dimensionless, Fedkiw et al. 2001; 0 = off). tolerance: the
    projection stops when the largest |divergence| is below this fraction of the one before it.
    """

    def __init__(self, box: Box, cells: int = 32, *, down: Vec3 = (0.0, -1.0, 0.0), buoyancy: float = 1.0,
                 vorticity: float = 0.0, tolerance: float = 1e-4,
                 max_iterations: int = 200) -> None:
        if not isinstance(box, Box):
            raise PhysicsInputError(f"box must be a Box, got {type(box).__name__}")
        if not isinstance(cells, int) or not AIR_CELLS[0] <= cells <= AIR_CELLS[1]:
            raise PhysicsInputError(f"cells must be an integer in {AIR_CELLS[0]}..{AIR_CELLS[1]}, got {cells!r}")
        for value, name in ((buoyancy, "buoyancy"), (vorticity, "vorticity")):
            if not isinstance(value, (int, float)) or not 0.0 <= value < float("inf"):
                raise PhysicsInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if not isinstance(tolerance, (int, float)) or not 0.0 < tolerance < 1.0:
            raise PhysicsInputError(f"tolerance must be in (0, 1), got {tolerance!r}")
        if not isinstance(max_iterations, int) or not 1 <= max_iterations <= 10_000:
            raise PhysicsInputError(f"max_iterations must be an integer in 1..10000, got {max_iterations!r}")
        self.box, self.cells = box, cells
        self.buoyancy, self.vorticity = float(buoyancy), float(vorticity)
        self.tolerance, self.max_iterations = float(tolerance), max_iterations
        self.floor = floor_face(down)
        extent = [hi - lo for lo, hi in zip(box.lo, box.hi)]
        self.spacing = max(extent) / cells
        self.shape: tuple[int, int, int] = tuple(  # type: ignore[assignment]
            max(MIN_CELLS_PER_AXIS, math.ceil(e / self.spacing - 1e-6)) for e in extent)
        self._bases: dict[torch.device, tuple[tuple[Tensor, Tensor, Tensor], Tensor]] = {}
        self._coords: dict[tuple[str, torch.device], Tensor] = {}  # face and cell-centre coordinates

    # --- state -----------------------------------------------------------------------------

    def still(self, device: torch.device | str = "cpu") -> AirState:
        """Air at rest on `device`."""
        nx, ny, nz = self.shape
        return AirState((torch.zeros(nx + 1, ny, nz, device=device), torch.zeros(nx, ny + 1, nz, device=device),
                         torch.zeros(nx, ny, nz + 1, device=device)), self.box.lo, self.spacing)

    def check(self, air: object) -> AirState:
        """`air` if it is a finite state of this grid (shape, corner and cell size), else a
        PhysicsInputError (e.g. air saved by a run on another grid)."""
        if not isinstance(air, AirState):
            raise PhysicsInputError(f"air must be an AirState, got {type(air).__name__}")
        for axis, face in enumerate(air.faces):
            expected = tuple(n + (a == axis) for a, n in enumerate(self.shape))
            if tuple(face.shape) != expected:
                raise PhysicsInputError(f"air.faces[{axis}] must have shape {expected} for this grid, "
                                        f"got {tuple(face.shape)}")
            if not bool(torch.isfinite(face).all()):
                raise PhysicsInputError(f"air.faces[{axis}] contains NaN or Inf")
        if not self._holds(air):
            raise PhysicsInputError(f"air lies on a grid at {tuple(air.origin)} with cells of {air.spacing:g}; this grid "
                                    f"starts at {self.box.lo} with cells of {self.spacing:g}")
        return air

    def _holds(self, air: AirState) -> bool:
        """Whether `air` lies on this grid: the same corner and cell size (its shape is `check`'s)."""
        return math.isclose(air.spacing, self.spacing, rel_tol=1e-6) and all(
            math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9 * self.spacing) for a, b in zip(air.origin, self.box.lo))

    def resample(self, air: AirState) -> AirState:
        """`air` if it lies on this grid, else its velocity sampled trilinearly at this grid's faces
        (the border value outside its grid) and projected: a continuation on a finer or coarser
        grid than its parent's goes on from the parent's air instead of from still air."""
        if self._holds(air):
            return self.check(air)
        for axis, face in enumerate(air.faces):
            if face.dim() != 3 or not bool(torch.isfinite(face).all()):
                raise PhysicsInputError(f"air.faces[{axis}] must be a finite 3-D array")
        if not (math.isfinite(air.spacing) and air.spacing > 0.0):
            raise PhysicsInputError(f"air.spacing must be a number > 0, got {air.spacing!r}")
        device = air.device
        origin = torch.tensor(air.origin, dtype=torch.float32, device=device)
        faces = []
        for a in range(3):
            world = self.face_positions(a, device)
            shape = [n + (b == a) for b, n in enumerate(self.shape)]
            faces.append(self._velocity(air.faces, (world - origin) / air.spacing)[:, a].reshape(shape))
        moved = AirState(tuple(faces), self.box.lo, self.spacing)  # type: ignore[arg-type]
        self.project(moved)
        return moved

    # --- sampling ----------------------------------------------------------------------------

    def velocity_at(self, air: AirState, points: Tensor) -> Tensor:
        """The air's velocity at `points` (N, 3), trilinear per component; points outside the grid
        take the value at its border."""
        return self._velocity(air.faces, self.grid_coords(points))

    def smoke_fraction(self, smoke: Tensor, config: PBFConfig) -> Tensor:
        """Fraction of each cell (nx, ny, nz) filled with smoke at the rest density: the particles
        (N, 3) splatted trilinearly onto the cell centres, times the volume one particle takes at
        rho0 (h^3 / (8 rho0), density 1 being 8 particles per h^3), over the cell volume; at most 1."""
        counts = splat(self.grid_coords(smoke) - 0.5, self.shape)
        return (counts * (config.h**3 / (8.0 * config.rho0 * self.spacing**3))).clamp(max=1.0)

    def divergence(self, air: AirState) -> Tensor:
        """Discrete divergence of the face velocities in each cell (nx, ny, nz), 1/s."""
        return sum(torch.diff(f, dim=a) for a, f in enumerate(air.faces)) / self.spacing  # type: ignore[return-value]

    def solid(self, spheres: Sequence[Sphere], time: float, device: torch.device) -> Tensor:
        """Cells (nx, ny, nz) whose centre lies inside a sphere at `time`."""
        centres = self._cell_centres(device)
        inside = torch.zeros(self.shape, dtype=torch.bool, device=device)
        for sphere in spheres:
            offset = centres - centres.new_tensor(sphere.center_at(time))
            inside |= (offset * offset).sum(-1) < sphere.radius**2
        return inside

    # --- the step ----------------------------------------------------------------------------

    def step(self, air: AirState, smoke: Tensor, config: PBFConfig, time: float,
             spheres: Sequence[Sphere] = (), force: ForceField | None = None,
             terminal_time: float | None = None) -> AirStats:
        """The paper model's air step (module docstring): advance `air` in place from `time` to
        `time + config.dt`, driven by the smoke particles `smoke` (N, 3) at `time` and the wind
        `force` (bounded by `terminal_time`, `accelerate`); the spheres are walls at `time + dt`
        (where the particles meet them)."""
        self.check(air)
        smoke = checks.points(smoke, "smoke").to(air.device)
        self.advect(air, config.dt)
        lift = None
        if smoke.shape[0]:
            fraction = self.buoyancy * self.smoke_fraction(smoke, config)
            lift = fraction[None] * fraction.new_tensor(config.body_acceleration)[:, None, None, None]
        self.accelerate(air, config.dt, config.speed_limit, cells=lift, force=force, terminal_time=terminal_time, time=time)
        return self.project(air, spheres, time + config.dt)

    def advect(self, air: AirState, dt: float) -> None:
        """Semi-Lagrangian self-advection of `air` in place over `dt` (`_advect`)."""
        air.faces = self._advect(air.faces, dt)  # type: ignore[assignment]

    def accelerate(self, air: AirState, dt: float, limit: float, *, cells: Tensor | None = None,
                   force: ForceField | None = None, terminal_time: float | None = None, time: float = 0.0) -> None:
        """Add dt x the body forces to `air` in place, then cap every face velocity at `limit`:
        `cells` (3, nx, ny, nz) an acceleration at the cell centres (the model's buoyancy), `force`
        a field evaluated at the faces at `time` (the wind) and the vorticity confinement. With
        `terminal_time` T the force f on a face whose air already moves at u along it is
        f (1 - (u / (T f))^2), 0 from u = T f on: a quadratic drag that holds the air it drives
        below the terminal velocity T f (`fluidcore.spec.controls.WindParams.terminal_speed`)."""
        confinement = self._confinement(air.faces) if self.vorticity > 0.0 else None
        faces = []
        for a, face in enumerate(air.faces):
            total = torch.zeros_like(face)
            if cells is not None:
                total = total + to_faces(cells[a], a)
            if confinement is not None:
                total = total + to_faces(confinement[a], a)
            if force is not None:
                total = total + bounded(self.force_on_faces(force, a, time, face), face, terminal_time)
            faces.append((face + dt * total).clamp(-limit, limit))
        air.faces = tuple(faces)  # type: ignore[assignment]

    def force_on_faces(self, force: ForceField, axis: int, time: float, like: Tensor) -> Tensor:
        """The `axis` component of `force` at the faces along `axis` at `time`, shaped like them."""
        positions = self.face_positions(axis, like.device)
        value = force(positions, time)
        if not isinstance(value, Tensor) or value.shape != positions.shape:
            raise PhysicsInputError(f"air force must return a tensor of shape {tuple(positions.shape)}")
        return checks.points(value, "air force(positions, time)")[:, axis].view(like.shape)

    def face_positions(self, axis: int, device: torch.device) -> Tensor:
        """World positions (F, 3) of the faces along `axis`, in their memory order."""
        return self.box_origin(device) + self.spacing * self._face_coords(axis, device)

    def diffuse(self, air: AirState, viscosity: float, dt: float) -> None:
        """Explicit diffusion of every face component in place: dv/dt = viscosity lap(v), world
        units^2 / s, in as many passes as keep each stable (viscosity dt / dx^2 <= 1/6 a pass);
        border faces see their own value beyond the grid (no flux through its ends)."""
        if viscosity <= 0.0:
            return
        number = viscosity * dt / self.spacing**2
        passes = max(1, math.ceil(number / DIFFUSION_STABLE))
        air.faces = tuple(_diffused(f, number / passes, passes) for f in air.faces)  # type: ignore[assignment]

    def project(self, air: AirState, spheres: Sequence[Sphere] = (), time: float = 0.0) -> AirStats:
        """Make `air` divergence-free in place, with the floor and the spheres at `time` as walls and
        the other box faces open (pressure 0 half a cell outside them)."""
        walls = self._walls(spheres, time, air.device)
        faces = tuple(torch.where(w > 0, f, v) for f, w, v in zip(air.faces, walls.weights, walls.velocities))
        air.faces = faces  # type: ignore[assignment]
        div = torch.where(walls.air, self.divergence(air), 0.0)
        before = float(div.abs().max())
        if before == 0.0:
            return AirStats(0, 0.0, 0.0)
        # Pressure phi (scaled by dt / density) solves L phi = -dx^2 div with
        # (L phi)_i = sum over faces of w_f (phi_i - phi_j); then u -= w grad(phi), div(u) = -r / dx^2.
        phi, iterations, converged = self._solve(-self.spacing**2 * div, walls)
        air.faces = tuple(f - w * gradient(phi, a) / self.spacing  # type: ignore[assignment]
                          for a, (f, w) in enumerate(zip(air.faces, walls.weights)))
        after = float(torch.where(walls.air, self.divergence(air), 0.0).abs().max())
        for face in air.faces:
            checks.finite_result(face, "air velocity")
        return AirStats(iterations, before, after, converged)

    # --- parts of the step -------------------------------------------------------------------

    def _advect(self, faces: tuple[Tensor, ...], dt: float) -> tuple[Tensor, ...]:
        """Semi-Lagrangian self-advection: each face takes the value found one step back along
        the velocity at the face (grid coordinates, clamped to the grid's border). The velocity at
        a face is averaged from its neighbours rather than interpolated: one trilinear sample per
        face instead of four (64 cells: 0.14 -> 0.05 CPU-s per step)."""
        centres = cell_velocity(faces)
        moved = []
        for a, face in enumerate(faces):
            # the velocity at these faces: its own component, the others averaged from the four around
            velocity = torch.stack([face if b == a else to_faces(centres[b], a) for b in range(3)], dim=-1)
            back = self._face_coords(a, face.device) - (dt / self.spacing) * velocity.reshape(-1, 3)
            moved.append(sample(face, back - face_offset(a, back)).view(face.shape))
        return tuple(moved)

    @staticmethod
    def _velocity(faces: Sequence[Tensor], s: Tensor) -> Tensor:
        """Velocity (N, 3) at grid coordinates s (N, 3): each component sampled on its own faces."""
        return torch.stack([sample(faces[b], s - face_offset(b, s)) for b in range(3)], dim=1)

    def _confinement(self, faces: tuple[Tensor, ...]) -> Tensor:
        """Vorticity confinement at the cell centres (3, nx, ny, nz): epsilon dx (N x omega),
        N the unit gradient of |omega| (re-injects the swirl that advection smooths away)."""
        omega = curl(cell_velocity(faces), self.spacing)
        grad = torch.stack(torch.gradient(torch.linalg.vector_norm(omega, dim=0), spacing=self.spacing))
        normal = grad / torch.linalg.vector_norm(grad, dim=0, keepdim=True).clamp_min(1e-12)
        return self.vorticity * self.spacing * torch.cross(normal, omega, dim=0)

    def _walls(self, spheres: Sequence[Sphere], time: float, device: torch.device) -> _Walls:
        solid = torch.zeros(self.shape, dtype=torch.bool, device=device)
        velocity = torch.zeros(3, *self.shape, device=device)
        for sphere in spheres:  # a later sphere wins where two overlap
            inside = self.solid((sphere,), time, device)
            solid |= inside
            velocity[:, inside] = velocity.new_tensor(sphere.velocity)[:, None]
        weights, velocities = [], []
        for a in range(3):
            padded = _pad_axis(solid, a, False)
            below, above = padded.narrow(a, 0, self.shape[a] + 1), padded.narrow(a, 1, self.shape[a] + 1)
            v = _pad_axis(velocity[a], a, 0.0)
            wall_v = torch.where(below, v.narrow(a, 0, self.shape[a] + 1), v.narrow(a, 1, self.shape[a] + 1))
            weight = (~(below | above)).float()
            if self.floor[0] == a:
                index = 0 if self.floor[1] == 0 else self.shape[a]
                weight.select(a, index).zero_()
                wall_v.select(a, index).zero_()
            weights.append(weight)
            velocities.append(wall_v)
        connected = sum(w.narrow(a, 0, self.shape[a]) + w.narrow(a, 1, self.shape[a]) for a, w in enumerate(weights))
        return _Walls(tuple(weights), tuple(velocities), ~solid & (connected > 0))  # type: ignore[arg-type]

    def _solve(self, b: Tensor, walls: _Walls) -> tuple[Tensor, int, bool]:
        """Preconditioned conjugate gradients for L phi = b on the air cells; the preconditioner
        is the exact inverse of the wall-free L (`_fast_inverse`). Stops when the largest residual
        is below tolerance x the largest |b| (phi, iterations, True), else after max_iterations
        (phi, max_iterations, False)."""
        mask = walls.air.float()
        b = b * mask
        goal = self.tolerance * float(b.abs().max())
        phi = torch.zeros_like(b)
        r = b.clone()
        z = mask * self._fast_inverse(r)
        p = z.clone()
        rz = (r * z).sum()
        for iteration in range(1, self.max_iterations + 1):
            ap = mask * laplacian(p, walls.weights)
            alpha = rz / (p * ap).sum().clamp_min(1e-30)
            phi = phi + alpha * p
            r = r - alpha * ap
            if float(r.abs().max()) <= goal:
                return phi, iteration, True
            z = mask * self._fast_inverse(r)
            rz_next = (r * z).sum()
            p = z + (rz_next / rz.clamp_min(1e-30)) * p
            rz = rz_next
        return phi, self.max_iterations, False

    def _fast_inverse(self, r: Tensor) -> Tensor:
        """L0^{-1} r for the wall-free Laplacian L0 = Tx + Ty + Tz (floor Neumann, rest Dirichlet):
        rotate into the product of the axes' eigenbases, divide by the eigenvalue sums, rotate back."""
        bases, eigen = self._basis(r.device)
        return rotate(rotate(r, bases, transpose=True) / eigen, bases, transpose=False)

    def _basis(self, device: torch.device) -> tuple[tuple[Tensor, Tensor, Tensor], Tensor]:
        if device not in self._bases:
            bases, values = [], []
            for a, n in enumerate(self.shape):
                closed = (self.floor == (a, 0), self.floor == (a, 1))
                lam, q = torch.linalg.eigh(axis_laplacian(n, closed))
                bases.append(q.float().to(device))
                values.append(lam.float().to(device))
            eigen = values[0][:, None, None] + values[1][None, :, None] + values[2][None, None, :]
            self._bases[device] = (tuple(bases), eigen)  # type: ignore[assignment]
        return self._bases[device]

    # --- coordinates -------------------------------------------------------------------------

    def box_origin(self, device: torch.device) -> Tensor:
        return torch.tensor(self.box.lo, dtype=torch.float32, device=device)

    def grid_coords(self, points: Tensor) -> Tensor:
        """World points (N, 3) in grid units: cell i spans [i, i+1) on each axis."""
        return (points - self.box_origin(points.device)) / self.spacing

    def _cell_centres(self, device: torch.device) -> Tensor:
        """World positions (nx, ny, nz, 3) of the cell centres."""
        key = ("centres", device)
        if key not in self._coords:
            axes = [torch.arange(n, device=device, dtype=torch.float32) + 0.5 for n in self.shape]
            grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
            self._coords[key] = self.box_origin(device) + self.spacing * grid
        return self._coords[key]

    def _face_coords(self, axis: int, device: torch.device) -> Tensor:
        """Grid coordinates (F, 3) of the faces along `axis`, in their memory order."""
        key = (f"faces{axis}", device)
        if key not in self._coords:
            shape = [n + (a == axis) for a, n in enumerate(self.shape)]
            self._coords[key] = face_coords(shape, axis, device)
        return self._coords[key]


def floor_face(down: Vec3) -> tuple[int, int]:
    """(axis, side) of the box face that `down` points through most: side 0 = the low face."""
    down = tuple(float(c) for c in down)  # type: ignore[assignment]
    if len(down) != 3 or not all(abs(c) < float("inf") for c in down) or not any(down):
        raise PhysicsInputError(f"down must be three finite numbers, not all 0, got {down!r}")
    axis = max(range(3), key=lambda a: abs(down[a]))
    return axis, 0 if down[axis] < 0 else 1


def axis_laplacian(n: int, closed: tuple[bool, bool]) -> Tensor:
    """The 1-D operator (n, n) of L along one axis: 2 on the diagonal, -1 beside it; an end that is
    a wall (no flux) has 1 on the diagonal, an open end keeps 2 (pressure 0 in the ghost cell)."""
    t = 2.0 * torch.eye(n, dtype=torch.float64) - torch.diag(torch.ones(n - 1, dtype=torch.float64), 1) \
        - torch.diag(torch.ones(n - 1, dtype=torch.float64), -1)
    if closed[0]:
        t[0, 0] = 1.0
    if closed[1]:
        t[-1, -1] = 1.0
    return t


def rotate(t: Tensor, bases: Sequence[Tensor], transpose: bool) -> Tensor:
    """Apply Q_x (x) Q_y (x) Q_z (or its transpose) to `t` (nx, ny, nz), one axis at a time
    (n^4 work on an n^3 grid, against n^6 for the assembled matrix)."""
    for a, q in enumerate(bases):
        t = torch.movedim(torch.tensordot(t, q if transpose else q.T, dims=([a], [0])), -1, a)
    return t


def cell_velocity(faces: Sequence[Tensor]) -> Tensor:
    """The face velocities averaged to the cell centres (3, nx, ny, nz)."""
    return torch.stack([0.5 * (f.narrow(a, 0, f.shape[a] - 1) + f.narrow(a, 1, f.shape[a] - 1))
                        for a, f in enumerate(faces)])


def curl(velocity: Tensor, spacing: float) -> Tensor:
    """Curl (3, nx, ny, nz) of a cell-centred velocity (3, nx, ny, nz), central differences inside."""
    d = [torch.gradient(velocity[c], spacing=spacing) for c in range(3)]  # d[c][k] = dU_c / dx_k
    return torch.stack([d[2][1] - d[1][2], d[0][2] - d[2][0], d[1][0] - d[0][1]])


def gradient(phi: Tensor, axis: int) -> Tensor:
    """phi_i - phi_{i-1} on the faces along `axis` (n+1 of them), phi = 0 outside the grid."""
    padded = _pad_axis(phi, axis, 0.0)
    return torch.diff(padded, dim=axis)


def laplacian(phi: Tensor, weights: Sequence[Tensor]) -> Tensor:
    """(L phi)_i = sum over the faces of cell i of w_f (phi_i - phi_neighbour), phi = 0 outside."""
    out = torch.zeros_like(phi)
    for a, w in enumerate(weights):
        flux = w * gradient(phi, a)
        out = out + flux.narrow(a, 0, phi.shape[a]) - flux.narrow(a, 1, phi.shape[a])
    return out


def to_faces(cells: Tensor, axis: int) -> Tensor:
    """Cell values (nx, ny, nz) averaged onto the faces along `axis`; a border face takes its one cell."""
    padded = torch.cat([cells.narrow(axis, 0, 1), cells, cells.narrow(axis, cells.shape[axis] - 1, 1)], dim=axis)
    return 0.5 * (padded.narrow(axis, 0, cells.shape[axis] + 1) + padded.narrow(axis, 1, cells.shape[axis] + 1))


def face_offset(axis: int, like: Tensor) -> Tensor:
    """Grid-unit offset (3,) of the faces along `axis` from the cell corner: 0 on `axis`, 1/2 on the others."""
    offset = like.new_full((3,), 0.5)
    offset[axis] = 0.0
    return offset


def face_coords(shape: torch.Size | Sequence[int], axis: int, device: torch.device) -> Tensor:
    """Grid coordinates (F, 3) of every face of a component grid of `shape`, in its memory order."""
    axes = [torch.arange(n, device=device, dtype=torch.float32) for n in shape]
    index = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return index + face_offset(axis, index)


def sample(field: Tensor, index: Tensor) -> Tensor:
    """Trilinear value of `field` (A, B, C) at fractional indices (N, 3), clamped to its border."""
    size = torch.tensor(field.shape, dtype=index.dtype, device=index.device) - 1.0
    normalised = 2.0 * index / size.clamp_min(1.0) - 1.0
    grid = normalised.flip(-1).view(1, -1, 1, 1, 3)  # grid_sample reads (W, H, D) = (C, B, A)
    out = F.grid_sample(field[None, None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(-1)


def splat(index: Tensor, shape: Sequence[int]) -> Tensor:
    """Trilinear splat of unit weights at fractional indices (N, 3) onto a grid of `shape`: the
    adjoint of `sample` (weights beyond the border land on the border cells)."""
    sizes = torch.tensor(shape, device=index.device)
    index = torch.minimum(index.clamp_min(0.0), (sizes - 1).to(index.dtype))
    base = torch.minimum(index.floor().long(), (sizes - 2).clamp_min(0))
    frac = index - base
    out = torch.zeros(int(sizes.prod()), dtype=index.dtype, device=index.device)
    strides = (shape[1] * shape[2], shape[2], 1)
    for corner in range(8):
        bits = [(corner >> a) & 1 for a in range(3)]
        weight = torch.ones_like(frac[:, 0])
        flat = torch.zeros_like(base[:, 0])
        for a, bit in enumerate(bits):
            weight = weight * (frac[:, a] if bit else 1.0 - frac[:, a])
            flat = flat + (base[:, a] + bit) * strides[a]
        out.index_add_(0, flat, weight)
    return out.view(*shape)


def bounded(force: Tensor, velocity: Tensor, terminal_time: float | None) -> Tensor:
    """`force` on air moving at `velocity` (the same component, the same faces), faded by a quadratic
    drag towards the terminal velocity terminal_time x force (`AirGrid.accelerate`); unchanged
    without a terminal time. Air moving against the force feels all of it."""
    if terminal_time is None:
        return force
    terminal = terminal_time * force
    ratio = torch.where(terminal != 0.0, velocity / torch.where(terminal != 0.0, terminal, 1.0), 0.0)
    return force * (1.0 - ratio.clamp(0.0, 1.0).square())


def _diffused(face: Tensor, number: float, passes: int) -> Tensor:
    """`face` (A, B, C) after `passes` explicit steps of dv = number x the 7-point Laplacian (edge
    values repeated beyond the border)."""
    for _ in range(passes):
        p = F.pad(face[None, None], (1, 1, 1, 1, 1, 1), mode="replicate")[0, 0]
        neighbours = (p[:-2, 1:-1, 1:-1] + p[2:, 1:-1, 1:-1] + p[1:-1, :-2, 1:-1] + p[1:-1, 2:, 1:-1]
                      + p[1:-1, 1:-1, :-2] + p[1:-1, 1:-1, 2:])
        face = face + number * (neighbours - 6.0 * face)
    return face


def _pad_axis(t: Tensor, axis: int, value: float | bool) -> Tensor:
    """`t` with one `value` slice added before and after along `axis`."""
    edge = torch.full_like(t.narrow(axis, 0, 1), value)
    return torch.cat([edge, t, edge], dim=axis)
