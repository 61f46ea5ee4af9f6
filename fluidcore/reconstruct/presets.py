"""Quality presets: how much work a reconstruction spends per frame, and at what resolution.

`paper` mirrors the paper and its official release: 250 optimiser iterations per frame (one
random view per iteration), full input resolution, the next-step incompressibility term on.
`preview` is what a CPU can do in minutes (docs/bench_reconstruct.md measures how few
iterations give the same PSNR); `standard` sits between them and is the GPU default.

Loss weights are the official release's: 0.8 L1 + 0.2 (1 - SSIM) for the image, 0.1 L_sim,
1.0 L_incomp, 0.1 next-step L_incomp; appearance regularisers lambda_c 10, lambda_s 0,
lambda_o 8, lambda_r 0.1 plus an anisotropy penalty. The optical-flow term (`flow`) is not the
release's: it compares the particles' projected motion with the input video's flow. The visual
layer's ties to the particles (one colour, one opacity, bounded extent) are this project's, not
the paper's (issue 12).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from fluidcore.errors import InputError


class PresetError(InputError):
    """An unknown preset name or an invalid override."""


@dataclass(frozen=True)
class LossWeights:
    l1: float = 0.8
    dssim: float = 0.2
    sim: float = 0.1
    incomp: float = 1.0
    incomp_next: float = 0.1
    color: float = 10.0  # lambda_c: temporal colour change
    scale: float = 0.0  # lambda_s
    opacity: float = 8.0  # lambda_o
    rotation: float = 0.1  # lambda_r
    anisotropy: float = 1.0
    max_anisotropy: float = 3.0  # scale ratio above which the anisotropy loss starts
    flow: float = 0.0  # input-view optical flow as a lower bound on the particles' projected motion
    # (reconstruct/flow.py); off: on the dev scene and ScalarFlow it did not lower the velocity error
    # and cost ScalarFlow 0.5 dB of future (docs/bench_generalise.md, "Optical flow")


MIN_FIT_SIDE = 8  # the smallest side, in pixels, the fit renders a view at (fluidcore.reconstruct.loop)


@dataclass(frozen=True)
class Quality:
    """Everything a reconstruction's cost depends on.

    Resolution is the rendered long side in pixels (the input's own when larger than it);
    `coarse_to_fine` are the fractions of it used in turn within a frame's position
    optimisation: coarse images constrain where smoke is cheaply, fine ones its detail.
    """

    name: str
    long_side: int
    position_iterations: int
    appearance_iterations: int
    first_frame_factor: int  # frame 0 starts from a simulated blob: give it this many times more
    coarse_to_fine: tuple[float, ...]
    particles_per_frame: int  # physical particles the source seeds per step
    velocity_radius: float  # visual Gaussians follow the velocity interpolated within this many h
    visual_per_physical: int  # visual Gaussians spawned per new physical particle
    next_step_incompressibility: bool
    symmetry_views: int  # plume-symmetry pseudo-views around the up axis (0 = off; single input view only)
    symmetry_weight: float  # their total loss weight relative to the input view
    # The long side (pixels) the symmetry pseudo-views are fitted at, where their working size is
    # larger (None: the input view's coarse-to-fine, as the input view). A round source makes the
    # plume's overall shape axisymmetric, not its puffs: at full resolution the prior copies the
    # input view's puffs to every azimuth, as rings that show as beads from the side. Off by
    # default: at 120 px (the one value tried, a quarter of preview's 480) ScalarFlow gained on every
    # seed of 0-2 (novel views +0.10 dB, future +0.39) and D stayed within 0.1 dB, but F lost 0.15
    # to 0.19 dB of novel views and 0.4 dB of its ball what-if on both seeds tried
    # (docs/bench_generalise.md, "The symmetry prior at a quarter of the resolution").
    symmetry_long_side: int | None = None
    initial_opacity: float = 0.3  # of a newborn visual Gaussian
    # The visual layer's ties to the particles (fluidcore.reconstruct.visual): a Gaussian's extent
    # (standard deviation per axis) stays within [min_scale, max_scale] kernel radii, from the
    # Poly6 kernel's own spread (1/sqrt(11) = 0.30 h) to its support; its opacity within
    # opacity_spread logits of the scene's one shared opacity (0: density only from where the
    # particles are; None: free per Gaussian, as before issue 12).
    min_scale: float = 0.3
    max_scale: float = 1.0
    opacity_spread: float | None = 0.0
    # In prediction each visual Gaussian follows the concentration of the smoke it carries
    # (fluidcore.smoke.Appearance.diluted: a parcel of fixed mass, lighter and wider as its
    # particles spread) instead of keeping its fitted opacity and extent. On: future +0.04 dB on
    # ScalarFlow, +0.08 on D, +0.09 on F (every seed of 0-2 gained; docs/bench_generalise.md,
    # "Opacity that follows the concentration"). The fit itself is not tied to it (that lost).
    opacity_concentration: bool = True
    # The air around the smoke (fluidcore.physics.air.AirGrid): cells on the box's long side, 0 = still
    # air (the default until issue 23's measurements on both dev scenes and ScalarFlow). The
    # reconstruction steps it frame by frame and saves it with every frame; continuations go on from it.
    air_cells: int = 0
    air_vorticity: float = 0.0  # the air's vorticity confinement (AirGrid's epsilon; 0 = off)
    # Identify the plume's spreading rate (entrainment, fluidcore.physics.entrainment) from the input
    # view and simulate it in every continuation; off: the paper's column (spreading rate 0). Off by
    # default: on, the predicted plume's width comes within 20% of the truth's on both dev scenes and
    # D's future gains 0.3 dB, but the wind what-ifs lose (F 0.9 dB); with the air grid too
    # (air_cells 32) the wind gains instead, but F's ball loses 0.6 dB (docs/bench_generalise.md,
    # "Entrainment").
    entrainment: bool = False
    lr_position: float = 0.02  # in units of h per iteration
    lr_color: float = 0.02
    lr_scale: float = 0.02
    lr_opacity: float = 0.05
    lr_rotation: float = 0.01
    weights: LossWeights = field(default_factory=LossWeights)
    seed: int = 0

    def __post_init__(self) -> None:
        side = self.symmetry_long_side
        if side is not None and (isinstance(side, bool) or not isinstance(side, int) or side < MIN_FIT_SIDE):
            raise PresetError(f"symmetry_long_side must be None or a whole number of pixels >= {MIN_FIT_SIDE}, got {side!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Quality:
        """Inverse of `to_json` (a run manifest's "quality"): a later stage that reconstructs
        again, like Algorithm S2's refinement, fits at the quality the run was made with."""
        return cls(**{**data, "coarse_to_fine": tuple(data["coarse_to_fine"]), "weights": LossWeights(**data["weights"])})

    def visual_settings(self) -> dict[str, Any]:
        """How the visual Gaussians move and are born: recorded in a reconstruction's manifest
        ("visual") so a prediction continues them alike without reading the preset back."""
        return {
            "velocity_radius": self.velocity_radius,
            "per_physical": self.visual_per_physical,
            "seed": self.seed,
            "opacity_concentration": self.opacity_concentration,
        }

    def with_overrides(self, **overrides: Any) -> Quality:
        """The preset with fields replaced; `weights` may be a mapping of just the loss weights
        to change (`--set 'weights={"flow": 1}'`)."""
        unknown = set(overrides) - set(self.__dataclass_fields__)
        if unknown:
            raise PresetError(f"quality overrides: unknown fields {sorted(unknown)}")
        weights = overrides.get("weights")
        if isinstance(weights, Mapping):
            bad = set(weights) - set(LossWeights.__dataclass_fields__)
            if bad:
                raise PresetError(f"quality overrides: unknown loss weights {sorted(bad)}")
            overrides = {**overrides, "weights": replace(self.weights, **weights)}
        return replace(self, **overrides)


PRESETS: dict[str, Quality] = {
    "preview": Quality(
        name="preview",
        long_side=480,
        position_iterations=20,
        appearance_iterations=10,
        first_frame_factor=4,
        coarse_to_fine=(0.5, 1.0),
        particles_per_frame=30,
        velocity_radius=2.0,
        visual_per_physical=2,
        next_step_incompressibility=False,
        symmetry_views=4,
        symmetry_weight=0.5,
    ),
    "standard": Quality(
        name="standard",
        long_side=1160,
        position_iterations=100,
        appearance_iterations=50,
        first_frame_factor=4,
        coarse_to_fine=(0.25, 0.5, 1.0),
        particles_per_frame=80,
        velocity_radius=2.0,
        visual_per_physical=4,
        next_step_incompressibility=True,
        symmetry_views=6,
        symmetry_weight=0.5,
    ),
    "paper": Quality(
        name="paper",
        long_side=100_000,  # i.e. the input's own resolution
        position_iterations=250,
        appearance_iterations=250,
        first_frame_factor=4,
        coarse_to_fine=(0.25, 0.5, 1.0),
        particles_per_frame=177,  # the release's ScalarFlow seeding
        velocity_radius=2.0,
        visual_per_physical=8,
        next_step_incompressibility=True,
        symmetry_views=6,
        symmetry_weight=0.5,
    ),
}


PHYSICS_MODES = {"auto": "scalarflow", "scalarflow": "scalarflow", "fluidnexus": "fluidnexus_smoke"}  # -> prior preset
DEFAULT_PHYSICS = "auto"  # identified from the input video (fluidcore.reconstruct.identify), the presets as priors
DEFAULT_QUALITY = "preview"  # what a job runs at when nobody says: the CLI, the API and the benchmarks alike
QUALITY_CHOICES = " | ".join(PRESETS)  # for help texts


def get(name: str) -> Quality:
    """The preset called `name`, or a PresetError naming the choices."""
    try:
        return PRESETS[name]
    except KeyError:
        raise PresetError(f"quality must be one of {', '.join(PRESETS)}, got {name!r}") from None



def reconstruction_quality(run) -> Quality | None:  # noqa: ANN001 - fluidcore.runs.Run
    """The quality of the reconstruction `run` is or descends from (its nearest reconstruct
    ancestor); None when there is none or it records none (a run made by hand or by a test)."""
    origin = run.reconstruction()
    recorded = None if origin is None else origin.settings.quality
    return Quality.from_json(recorded) if recorded else None
