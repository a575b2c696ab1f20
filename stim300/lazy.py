"""Names of a package loaded when first used (PEP 562): `import stim300` or `import calibd` costs
no numpy, scipy or DDS import until a name that needs one is asked for."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, homes: dict[str, str]):
    """The module `__getattr__` of `package` that finds each public name of `homes` (name ->
    the submodule that defines it) in its submodule at first use."""
    def __getattr__(name: str):
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f".{homes[name]}", package), name)
    return __getattr__
