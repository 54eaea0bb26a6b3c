"""Names a package exports, imported from their modules on first use (PEP 562).

A package lists its names once; ``import`` of the package loads none of their modules, so
the console script starts without numpy, scipy or torch and pays only for what a command uses.
Each look-up goes to the module that holds the name.
"""

import importlib
from collections.abc import Callable, Mapping


def lazy_exports(package: str, names: Mapping[str, tuple[str, ...]]) -> tuple[Callable, Callable, list[str]]:
    """Return a package's ``__getattr__``, ``__dir__`` and ``__all__`` for ``{module: names}``.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    names : mapping of str to tuple of str
        For each module, relative to the package (``"_optics"``), the names it exports.
    """
    module_of = {name: module for module, exported in names.items() for name in exported}
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        if name in module_of:
            # not cached in the package: a name replaced in its module (a test's monkeypatch) is seen at once
            return getattr(importlib.import_module(f"{package}.{module_of[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(module_of))

    return __getattr__, __dir__, list(module_of)
