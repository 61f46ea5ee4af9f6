"""The names of a run folder's files, its format and its kinds: the one place that spells them
(the layout itself is described in `fluidcore.runs`)."""

from __future__ import annotations

import enum

from fluidcore.errors import InputError

FORMAT = "fluidnexus-run"
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
MANIFEST = "manifest.json"
BACKGROUND = "background.npz"
STATES_DIR = "states"
REFINED_RUN = "refined"  # sub-run of a prediction: the reconstruction on its video-model-refined frames


class RunError(InputError):
    """A run folder that is missing, damaged, or holds a different run than expected."""


class RunKind(enum.StrEnum):
    """What wrote a run. The service's job types (`service.job_types.JobType`) are these kinds:
    each job writes the run of its own kind."""

    RECONSTRUCT = "reconstruct"
    PREDICT = "predict"
    INTERACT = "interact"
    RESIMULATE = "resimulate"


def state_file(t: int) -> str:
    """Where frame t's state lies in a run folder (relative, POSIX): the one place that knows."""
    return f"{STATES_DIR}/frame_{t:06d}.npz"
