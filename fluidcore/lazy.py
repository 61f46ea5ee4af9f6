"""Package faces that load their torch-backed modules on first use (PEP 562 `__getattr__`).

`fluidcore.physics`, `fluidcore.reconstruct` and `fluidcore.predict` export their torch-backed
names through `lazy_exports`, so a torch-free caller (the API reading a preset, a physics
configuration or a run's scene) imports the package without loading torch.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping


def lazy_exports(package: str, homes: Mapping[str, str]) -> Callable[[str], object]:
    """A module `__getattr__` for `package` that imports `package.homes[name]` when `name` is first asked for."""

    def __getattr__(name: str) -> object:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)

    return __getattr__
