"""A package's public names imported on first use (PEP 562), so that importing one of its modules, or the
command line, does not pay for what it does not use (JAX above all)."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable


def lazy_exports(package: str, public: dict[str, str]) -> tuple[Callable, Callable, list[str]]:
    """``(__getattr__, __dir__, __all__)`` for ``package`` whose public ``name → submodule`` are ``public``
    (a submodule's name, or a relative module path such as ``"..io.board"``); a name is imported from its
    module when first looked up and then kept in the package."""

    def __getattr__(name: str):
        module = public.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module if module.startswith(".") else f".{module}", package), name)
        setattr(sys.modules[package], name, value)  # later lookups do not come here
        return value

    names = sorted(public)

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return __getattr__, __dir__, names
