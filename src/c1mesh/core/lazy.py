"""Modules imported on first use: scipy, for the stages that need it.

A plain fit (a LAS/LAZ or PLY to a mesh) needs no scipy, and importing scipy's sparse,
spatial and ndimage packages costs about 0.27 s of every command's start (a small file's
whole fit takes 0.5 s). The modules that use scipy name it at their top as a LazyModule,
which imports it the first time one of its attributes is asked for.

Why not importlib.util.LazyLoader (or the lazy_loader package, which uses it): on
Python 3.11 a lazily loaded module's attributes can be asked for by a second thread
while the first one is still loading it, and that thread then sees a half-initialised
module (python/cpython#114763, scientific-python/lazy-loader#88). Here every first use
goes through importlib.import_module, whose per-module import lock makes the other
threads wait for the whole module.
"""
from __future__ import annotations

import importlib
from types import ModuleType


class LazyModule:
    """The module `name`, imported when an attribute of it is first asked for
    (`spatial = LazyModule("scipy.spatial")`, then `spatial.cKDTree(...)`)."""

    def __init__(self, name: str):
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attribute: str):
        module = self._module
        if module is None:                       # importlib's lock: one thread imports, others wait
            module = self._module = importlib.import_module(self._name)
        return getattr(module, attribute)

    def __repr__(self) -> str:
        return f"<LazyModule {self._name!r} ({'imported' if self._module is not None else 'not yet imported'})>"
