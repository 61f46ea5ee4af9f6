"""The one rule for names a user supplies that may become part of a file path or a storage key,
and the one path join that every such name goes through.

A camera's name becomes `<name>.mp4` in the worker's folder and a storage key, an uploaded
file's name becomes a file in the upload folder, a cameras file's `file_path` is looked up
beside it. A name that means a path (`../x`, `/tmp/x`) would let one user write over another
user's files; so would anything a later layer might decode or normalise into one
(`%2e%2e%2f`, a fullwidth solidus U+FF0F that NFKC folds to '/', a NUL that C truncates at, a
backslash that Windows splits at). Rather than list the bad forms, the rule lists the good
ones: plain ASCII letters, digits, '.', '_' and '-', so no decoding or normalisation can turn
an accepted name into a separator, and a right-to-left override cannot make a name display as
another. Names are checked where they enter (the API, the CLI, the camera readers) and refused
with a message naming the field; `safe_join` then refuses, independently, any joined path that
resolves outside its root (defence in depth: a name check can be missed, a symlink cannot be
seen in a name). Both refusals are `InputError`s: shown to the user as they are. Torch-free;
the API imports it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

from fluidcore.errors import InputError

NAME_MAX_CHARS = 64
RELATIVE_MAX_PARTS = 8  # "sparse/0/cameras.bin" has 3; deeper is no capture layout we know
# Device names Windows reserves in every folder, with any extension and in any case ("con.mp4" opens
# the console): a run folder or a storage bucket copied to a Windows or SMB volume could not hold them.
RESERVED_NAMES = frozenset({"con", "prn", "aux", "nul", *(f"com{i}" for i in range(1, 10)), *(f"lpt{i}" for i in range(1, 10))})
NAME_RULE = (
    f"1 to {NAME_MAX_CHARS} characters from A-Z a-z 0-9 '.' '_' '-', starting with a letter or digit, without '..', "
    "not a device name (CON, PRN, AUX, NUL, COM1-9, LPT1-9)"
)
# First a letter or digit: not '.' (hidden files, '.', '..') and not '-' (read as an option by tools).
_NAME = re.compile(rf"[A-Za-z0-9][A-Za-z0-9._-]{{0,{NAME_MAX_CHARS - 1}}}")


class UnsafeName(InputError):
    """A user-supplied name breaks the naming rule; the message names the field and the rule."""


class UnsafePath(InputError):
    """A joined path would lie outside its root (its message names the parts, never the root)."""


def is_safe_name(value: object) -> bool:
    """True when `value` is a str that follows NAME_RULE (see the module docstring)."""
    return (isinstance(value, str) and _NAME.fullmatch(value) is not None and ".." not in value
            and value.split(".", 1)[0].lower() not in RESERVED_NAMES)


def case_twin(names: Iterable[str], name: str) -> str | None:
    """The one of `names` that differs from `name` in case alone, if any: case-insensitive file
    systems (macOS's and Windows' defaults) store `Cam0.mp4` and `cam0.mp4` as one file."""
    return next((other for other in names if other != name and other.casefold() == name.casefold()), None)


def check_name(value: object, field: str) -> str:
    """`value` if it is a safe name (NAME_RULE), else UnsafeName naming `field`."""
    if not is_safe_name(value):
        raise UnsafeName(f"{field}: {value!r} is not an accepted name; use {NAME_RULE}")
    return value  # type: ignore[return-value]  # is_safe_name checked it is a str


def check_relative(value: object, field: str) -> str:
    """`value` if it is a '/'-separated relative path of at most RELATIVE_MAX_PARTS safe names
    (a cameras file's `file_path`, a zip member, an artifact name like `videos/cam0.mp4`)."""
    parts = value.split("/") if isinstance(value, str) else []
    if not 1 <= len(parts) <= RELATIVE_MAX_PARTS or not all(is_safe_name(part) for part in parts):
        raise UnsafeName(
            f"{field}: {value!r} is not an accepted relative path; use up to {RELATIVE_MAX_PARTS} "
            f"'/'-separated names of {NAME_RULE}"
        )
    return value  # type: ignore[return-value]


def safe_join(root: str | os.PathLike[str], *parts: str) -> Path:
    """`root` joined with `parts`, resolved (symlinks followed), refused with UnsafePath unless
    the result lies strictly inside the resolved `root`.

    Every join of a user-influenced name goes through here, even after `check_name`: it also
    catches a symlink planted inside `root` and a name a caller forgot to check."""
    base = Path(root).resolve()
    if any("\0" in part for part in parts):
        raise UnsafePath(f"{'/'.join(parts)!r}: a NUL character in a path")
    target = base.joinpath(*parts).resolve()
    if target == base or not target.is_relative_to(base):
        raise UnsafePath(f"{'/'.join(parts)!r} escapes its folder")
    return target
