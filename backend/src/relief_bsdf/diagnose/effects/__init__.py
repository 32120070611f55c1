"""Candidate effects of the diagnosis: one module per effect, found by discovery.

Each public module of this package (name = the formats.md effect name) holds one
`EFFECT = Effect(...)` (see `_base`): its parameters, physics, validity, how it changes
the plate description (`plate.description.Experiment`) and its explanation text.  Adding
an effect is adding one module here; nothing else lists effects.
"""
from __future__ import annotations

import importlib
import pkgutil

from relief_bsdf.diagnose.effects._base import Effect, Param, ReliefContext, apply_all, compatible

__all__ = ["Effect", "Param", "ReliefContext", "all_effects", "apply_all", "compatible", "get_effect"]

_REGISTRY: dict[str, Effect] = {}


def all_effects() -> dict[str, Effect]:
    """{name: Effect} of every effect module of this package, in name order."""
    if not _REGISTRY:
        found = {}
        for info in pkgutil.iter_modules(__path__):
            if info.name.startswith("_"):
                continue
            mod = importlib.import_module(f"{__name__}.{info.name}")
            eff = getattr(mod, "EFFECT", None)
            if not isinstance(eff, Effect) or eff.name != info.name:
                raise RuntimeError(f"effect module {info.name} must define EFFECT = Effect(name={info.name!r}, ...)")
            found[eff.name] = eff
        _REGISTRY.update(sorted(found.items()))
    return dict(_REGISTRY)


def get_effect(name: str) -> Effect:
    effects = all_effects()
    if name not in effects:
        raise KeyError(name)
    return effects[name]
