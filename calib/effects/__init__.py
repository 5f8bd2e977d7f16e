"""Physical effects the rigid model leaves out, as composable additions to the measurement model (issue 7).

Public API:

* :class:`Effect`, :class:`ParamSpec`: what an effect is (see :mod:`calib.effects.base`);
* :class:`EffectModel` ``(robot, effects)``: the measurement model with effects, a drop-in for
  ``calib.selfcal.model.MeasurementModel``;
* :func:`available_effects` ``(extra_files=()) -> dict[name, Effect class]``: the built-in library, the
  effects installed under the entry-point group ``cdpr.effects`` and those defined in the given files;
* :func:`make_effects` ``(names, available=None) -> list[Effect]``: instances by name, in order;
* :func:`load_effect_file` ``(path) -> dict[name, Effect class]``: the Effect subclasses of a Python file.
"""

from __future__ import annotations

import importlib.util
import inspect
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from calib.effects.base import Context, Effect, EffectModel, Implausible, ParamSpec, Physical, Projected
from calib.errors import CdprError

ENTRY_POINT_GROUP = "cdpr.effects"


def __getattr__(name: str) -> Any:
    """``BUILTIN``, the library (the rigid-model corrections of issue 7, the cable-transmission effects of
    issue 17, then the swivel-pulley geometry of issue 28), built on first use: a solve that only needs the
    model and the device priors does not import the three modules of candidates (PEP 562)."""
    if name == "BUILTIN":
        from calib.effects import builtin, cable, swivel

        library: dict[str, type[Effect]] = {**builtin.BUILTIN, **cable.CABLE, **swivel.SWIVEL}
        globals()["BUILTIN"] = library
        return library
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "Context",
    "Effect",
    "EffectModel",
    "EffectLoadError",
    "Implausible",
    "ParamSpec",
    "Physical",
    "Projected",
    "available_effects",
    "load_effect_file",
    "make_effects",
]


class EffectLoadError(CdprError, ValueError):
    """An effect that cannot be loaded or named (the message names the file or the name)."""


def _effect_classes(namespace: Iterable) -> dict[str, type[Effect]]:
    out = {}
    for obj in namespace:
        if inspect.isclass(obj) and issubclass(obj, Effect) and obj is not Effect and getattr(obj, "name", ""):
            out[obj.name] = obj
    return out


def load_effect_file(path: str | Path) -> dict[str, type[Effect]]:
    """The Effect subclasses (with a ``name``) defined in a Python file, by name."""
    p = Path(path)
    if not p.is_file():
        raise EffectLoadError(f"{p}: effect file not found.")
    spec = importlib.util.spec_from_file_location(f"cdpr_user_effects_{abs(hash(str(p.resolve())))}", p)
    if spec is None or spec.loader is None:
        raise EffectLoadError(f"{p}: not a Python file that can be imported.")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a user's file: any error is reported as one sentence
        raise EffectLoadError(f"{p}: importing the effect file failed ({type(exc).__name__}: {exc}).") from exc
    found = {n: c for n, c in _effect_classes(vars(module).values()).items() if c.__module__ == module.__name__}
    if not found:
        raise EffectLoadError(f"{p}: defines no subclass of calib.effects.Effect with a 'name'.")
    return found


def _entry_point_effects() -> dict[str, type[Effect]]:
    from importlib.metadata import entry_points  # 0.1-0.2 s: only when the installed effects are listed

    out: dict[str, type[Effect]] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken plug-in must not break the built-in library
            raise EffectLoadError(
                f"entry point '{ep.name}' of group {ENTRY_POINT_GROUP} failed to load: {exc}."
            ) from exc
        if inspect.ismodule(obj):
            out.update(_effect_classes(vars(obj).values()))
        elif inspect.isclass(obj) and issubclass(obj, Effect):
            out[getattr(obj, "name", "") or ep.name] = obj
    return out


def available_effects(extra_files: Sequence[str | Path] = ()) -> dict[str, type[Effect]]:
    """Built-in effects, then the installed plug-ins (``cdpr.effects`` entry points), then the files'."""
    out: dict[str, type[Effect]] = dict(__getattr__("BUILTIN"))
    out.update(_entry_point_effects())
    for f in extra_files:
        out.update(load_effect_file(f))
    return out


def make_effects(names: Sequence[str], available: dict[str, type[Effect]] | None = None) -> list[Effect]:
    """Instances of the named effects, in the given order."""
    avail = __getattr__("BUILTIN") if available is None else available
    out = []
    for name in names:
        if name not in avail:
            raise EffectLoadError(f"unknown effect '{name}' (known: {', '.join(avail)}).")
        out.append(avail[name]())
    return out
