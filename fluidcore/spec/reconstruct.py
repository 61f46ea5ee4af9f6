"""What a reconstruction spends and fits: `ReconstructConfig` and the quality presets.

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

The config is nested by who reads each part, so a reader takes only its part: `fit` (the budget:
resolution, iterations, particles; the loop), `visual` (how the visual Gaussians are born, move
and look; the loop, and every continuation through `VisualSettings`), `priors` (the extra terms
and pseudo-views a fit adds where one view says too little), `optimiser` (learning rates),
`weights` (the loss weights) and `simulation` (what the simulator adds, which the user may switch
on: fluidcore.spec.simulation). Every field is checked where a config is made; `with_overrides`
(the benchmarks' `--set`) goes through the same checks.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, model_validator

from fluidcore.errors import InputError, describe_validation
from fluidcore.spec.simulation import SimulationConfig

MIN_FIT_SIDE = 8  # the smallest side, in pixels, the fit renders a view at (fluidcore.reconstruct.loop)

_SPEC = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
# Numbers and switches as they are written (a JSON number, true/false): "120" or true is no count
# of pixels. Whole numbers are still taken where a real is meant (`weights={"flow": 1}`).
Int = Annotated[int, Strict()]
Real = Annotated[float, Strict()]
Switch = Annotated[bool, Strict()]
Weight = Annotated[float, Strict(), Field(ge=0.0)]
Rate = Annotated[float, Strict(), Field(gt=0.0)]


class PresetError(InputError):
    """An unknown preset name or an invalid override; the message names the field."""


class LossWeights(BaseModel):
    """The loss terms' weights (module docstring: the release's values); 0 switches a term off."""

    model_config = _SPEC
    l1: Weight = 0.8
    dssim: Weight = 0.2
    sim: Weight = 0.1
    incomp: Weight = 1.0
    incomp_next: Weight = 0.1
    color: Weight = 10.0  # lambda_c: temporal colour change
    scale: Weight = 0.0  # lambda_s
    opacity: Weight = 8.0  # lambda_o
    rotation: Weight = 0.1  # lambda_r
    anisotropy: Weight = 1.0
    max_anisotropy: Real = Field(default=3.0, ge=1.0)  # scale ratio above which the anisotropy loss starts
    flow: Weight = 0.0  # input-view optical flow as a lower bound on the particles' projected motion
    # (reconstruct/flow.py); off: on the dev scene and ScalarFlow it did not lower the velocity error
    # and cost ScalarFlow 0.5 dB of future (docs/bench_generalise.md, "Optical flow")


class FitBudget(BaseModel):
    """What a reconstruction's cost depends on. Resolution is the rendered long side in pixels
    (the input's own when larger than it); `coarse_to_fine` are the fractions of it used in turn
    within a frame's position optimisation: coarse images constrain where smoke is cheaply, fine
    ones its detail. The particle budget is here, not in the simulation settings: it sets how many
    particles the fit moves, and so its cost, and caps the inlet the identification may choose."""

    model_config = _SPEC
    long_side: Int = Field(ge=MIN_FIT_SIDE)
    position_iterations: Int = Field(ge=1)
    appearance_iterations: Int = Field(ge=1)
    first_frame_factor: Int = Field(ge=1)  # frame 0 starts from a simulated blob: give it this many times more
    coarse_to_fine: tuple[Annotated[float, Strict(), Field(gt=0.0, le=1.0)], ...] = Field(min_length=1)
    particles_per_frame: Int = Field(ge=1)  # most particles the source seeds per 1/30 s (per frame at 30 fps; scene_physics.frame_budget)

    @model_validator(mode="after")
    def _coarse_first(self) -> FitBudget:
        if list(self.coarse_to_fine) != sorted(set(self.coarse_to_fine)):
            raise ValueError(f"coarse_to_fine must be fractions of the long side from coarse to fine, got {list(self.coarse_to_fine)}")
        return self


class VisualConfig(BaseModel):
    """The visual layer: how the visual Gaussians follow the particles, are born and look.

    Its ties to the particles (fluidcore.reconstruct.visual): a Gaussian's extent (standard
    deviation per axis) stays within [min_scale, max_scale] kernel radii, from the Poly6 kernel's
    own spread (1/sqrt(11) = 0.30 h) to its support; its opacity within opacity_spread logits of
    the scene's one shared opacity (0: density only from where the particles are; None: free per
    Gaussian, as before issue 12).
    """

    model_config = _SPEC
    velocity_radius: Real = Field(default=2.0, gt=0.0)  # visual Gaussians follow the velocity interpolated within this many h
    per_physical: Int = Field(ge=1)  # visual Gaussians spawned per new physical particle
    initial_opacity: Real = Field(default=0.3, gt=0.0, lt=1.0)  # of a newborn visual Gaussian
    min_scale: Real = Field(default=0.3, gt=0.0)
    max_scale: Real = Field(default=1.0, gt=0.0)
    opacity_spread: Real | None = Field(default=0.0, ge=0.0)
    # In prediction each visual Gaussian follows the concentration of the smoke it carries
    # (fluidcore.smoke.Appearance.diluted: a parcel of fixed mass, lighter and wider as its
    # particles spread) instead of keeping its fitted opacity and extent. On: future +0.04 dB on
    # ScalarFlow, +0.08 on D, +0.09 on F (every seed of 0-2 gained; docs/bench_generalise.md,
    # "Opacity that follows the concentration"). The fit itself is not tied to it (that lost).
    opacity_concentration: Switch = True

    @model_validator(mode="after")
    def _scale_bounds(self) -> VisualConfig:
        if self.max_scale < self.min_scale:
            raise ValueError(f"max_scale ({self.max_scale}) must not be below min_scale ({self.min_scale})")
        return self


class PriorConfig(BaseModel):
    """What a fit adds where its views say too little: the plume's symmetry as pseudo-views (for a
    single input view) and the next-step incompressibility term."""

    model_config = _SPEC
    symmetry_views: Int = Field(ge=0)  # plume-symmetry pseudo-views around the up axis (0 = off; single input view only)
    symmetry_weight: Weight  # their total loss weight relative to the input view
    # The long side (pixels) the symmetry pseudo-views are fitted at, where their working size is
    # larger (None: the input view's coarse-to-fine, as the input view). A round source makes the
    # plume's overall shape axisymmetric, not its puffs: at full resolution the prior copies the
    # input view's puffs to every azimuth, as rings that show as beads from the side. Off by
    # default: at 120 px (the one value tried, a quarter of preview's 480) ScalarFlow gained on every
    # seed of 0-2 (novel views +0.10 dB, future +0.39) and D stayed within 0.1 dB, but F lost 0.15
    # to 0.19 dB of novel views and 0.4 dB of its ball what-if on both seeds tried
    # (docs/bench_generalise.md, "The symmetry prior at a quarter of the resolution").
    symmetry_long_side: Int | None = Field(default=None, ge=MIN_FIT_SIDE)
    next_step_incompressibility: Switch


class OptimiserConfig(BaseModel):
    """The optimisers' learning rates, per iteration."""

    model_config = _SPEC
    lr_position: Rate = 0.02  # in units of h per iteration
    lr_color: Rate = 0.02
    lr_scale: Rate = 0.02
    lr_opacity: Rate = 0.05
    lr_rotation: Rate = 0.01


class VisualSettings(BaseModel):
    """What a continuation needs of the reconstruction's visual layer to move and bear visual
    Gaussians as the fit did (`ReconstructConfig.visual_settings`), recorded with every
    continuation so a chain of them carries it without reading the reconstruction back."""

    model_config = _SPEC
    velocity_radius: Real = Field(gt=0.0)
    per_physical: Int = Field(ge=1)
    seed: Int
    opacity_concentration: Switch = False  # opacity follows the smoke's concentration; runs before it: fixed


class ReconstructConfig(BaseModel):
    """Everything a reconstruction's result depends on besides its inputs: a preset (`get`), with
    overrides where a benchmark or the user's simulation settings change it."""

    model_config = _SPEC
    name: str = Field(min_length=1)
    seed: Int = 0
    fit: FitBudget
    visual: VisualConfig
    priors: PriorConfig
    optimiser: OptimiserConfig = OptimiserConfig()
    weights: LossWeights = LossWeights()
    simulation: SimulationConfig = SimulationConfig()

    def visual_settings(self) -> VisualSettings:
        """What a continuation of a run made with this config keeps of its visual layer."""
        return VisualSettings(velocity_radius=self.visual.velocity_radius, per_physical=self.visual.per_physical,
                              seed=self.seed, opacity_concentration=self.visual.opacity_concentration)

    def with_simulation(self, simulation: SimulationConfig) -> ReconstructConfig:
        """This config with `simulation` (the user's) in place of its own; of a request model that
        extends `SimulationConfig` (the API's reconstruct parameters) only those settings."""
        own = SimulationConfig(**{name: getattr(simulation, name) for name in SimulationConfig.model_fields})
        return self.model_copy(update={"simulation": own})

    def with_overrides(self, **overrides: Any) -> ReconstructConfig:
        """This config with fields replaced, each checked as where a config is made. A key is a
        dotted path (`fit.long_side`, `weights.flow`) or a field's own name where only one part
        has it (`long_side`, `seed`, `air_cells`); a part given a mapping keeps what it does not
        name (`weights={"flow": 1}`)."""
        data = self.model_dump()
        for key, value in overrides.items():
            path = _override_path(key)
            part, leaf = _holder(data, path), path[-1]
            part[leaf] = {**part[leaf], **value} if isinstance(part[leaf], dict) and isinstance(value, Mapping) else value
        try:
            return ReconstructConfig.model_validate(data)
        except ValidationError as exc:
            raise PresetError(f"quality overrides: {describe_validation(exc)}") from None


# A field's own name reaches it where it is unambiguous: every part's fields have names found in
# no other part and not at the top, which these lines check on import. The loss weights are left
# out: `color` or `scale` alone would not say that a weight is meant.
_PARTS = {name: field.annotation for name, field in ReconstructConfig.model_fields.items()
          if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel) and name != "weights"}
_FLAT = {leaf: (part, leaf) for part, model in _PARTS.items() for leaf in model.model_fields}
assert not set(_FLAT) & set(ReconstructConfig.model_fields), "a flat override name would be ambiguous"
assert len(_FLAT) == sum(len(model.model_fields) for model in _PARTS.values()), "a flat override name would be ambiguous"


def _override_path(key: str) -> tuple[str, ...]:
    """Where override `key` lands in the nested config (`ReconstructConfig.with_overrides`)."""
    if key in ReconstructConfig.model_fields:
        return (key,)
    if key in _FLAT:
        return _FLAT[key]
    path = tuple(key.split("."))
    model: Any = ReconstructConfig
    for name in path:
        if not (isinstance(model, type) and issubclass(model, BaseModel) and name in model.model_fields):
            raise PresetError(f"quality overrides: unknown field {key!r}")
        model = model.model_fields[name].annotation
    return path


_RENAMED = {"visual_per_physical": "per_physical"}  # flat names of run format 1 and 2 that became others


def quality_fields(recorded: Mapping[str, Any]) -> dict[str, Any]:
    """The fields of a quality as any version recorded it, nested for `ReconstructConfig.
    model_validate`: as they are, or nested from a flat record (one dict of every field: run
    format 1 and 2, and the benchmarks' JSON of that time), whose left-out fields take the default
    and whose fields of features removed since (`air_flow`, `depth_candidates`) are dropped."""
    if "fit" in recorded:
        return dict(recorded)
    nested: dict[str, Any] = {}
    for key, value in recorded.items():
        name = _RENAMED.get(key, key)
        if name not in _FLAT and name not in ReconstructConfig.model_fields:
            continue
        path = _FLAT.get(name, (name,))
        _holder(nested, path)[path[-1]] = value
    return nested


def _holder(tree: dict[str, Any], path: tuple[str, ...]) -> dict[str, Any]:
    """The dict of the nested `tree` that holds `path`'s last name (its parts made where missing)."""
    for name in path[:-1]:
        tree = tree.setdefault(name, {})
    return tree


@dataclass(frozen=True)
class Preset:
    """A named config and the one line that says what it is for (help texts, API descriptions)."""

    config: ReconstructConfig
    description: str


PRESETS: dict[str, Preset] = {
    "preview": Preset(ReconstructConfig(
        name="preview",
        fit=FitBudget(long_side=480, position_iterations=20, appearance_iterations=10, first_frame_factor=4,
                      coarse_to_fine=(0.5, 1.0), particles_per_frame=30),
        visual=VisualConfig(velocity_radius=2.0, per_physical=2),
        priors=PriorConfig(symmetry_views=4, symmetry_weight=0.5, next_step_incompressibility=False),
    ), "what a CPU reconstructs in minutes"),
    "standard": Preset(ReconstructConfig(
        name="standard",
        fit=FitBudget(long_side=1160, position_iterations=100, appearance_iterations=50, first_frame_factor=4,
                      coarse_to_fine=(0.25, 0.5, 1.0), particles_per_frame=80),
        visual=VisualConfig(velocity_radius=2.0, per_physical=4),
        priors=PriorConfig(symmetry_views=6, symmetry_weight=0.5, next_step_incompressibility=True),
    ), "the GPU default, between preview and paper"),
    "paper": Preset(ReconstructConfig(
        name="paper",
        fit=FitBudget(
            long_side=100_000,  # i.e. the input's own resolution
            position_iterations=250, appearance_iterations=250, first_frame_factor=4, coarse_to_fine=(0.25, 0.5, 1.0),
            particles_per_frame=177,  # the release's ScalarFlow seeding
        ),
        visual=VisualConfig(velocity_radius=2.0, per_physical=8),
        priors=PriorConfig(symmetry_views=6, symmetry_weight=0.5, next_step_incompressibility=True),
    ), "the paper's and its release's budget, at the input's own resolution"),
}

DEFAULT_QUALITY = "preview"  # what a job runs at when nobody says: the CLI, the API and the benchmarks alike
QUALITY_HELP = "; ".join(f"{name}: {preset.description}" for name, preset in PRESETS.items())  # the choices, said


def get(name: str) -> ReconstructConfig:
    """The preset called `name`, or a PresetError naming the choices."""
    try:
        return PRESETS[name].config
    except KeyError:
        raise PresetError(f"quality must be one of {', '.join(PRESETS)}, got {name!r}") from None
