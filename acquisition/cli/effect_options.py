"""The command line's effect options, shared by `cdpr diagnose` (one run or several) and `cdpr solve`: the
effect classes a command may name and the parsing of an --effects list."""

from __future__ import annotations

import importlib
from pathlib import Path

from acquisition.cli.errors import UsageError
from calib.effects import Effect, EffectLoadError, available_effects, make_effects


def effect_classes(sources: list[str]) -> dict[str, type[Effect]]:
    """Built-in, installed (entry points) and --effects-from effects; a source is a file or a module name."""
    files, modules = [], []
    for s in sources:
        (files if s.endswith(".py") or Path(s).is_file() else modules).append(s)
    try:
        out = available_effects(files)
    except EffectLoadError as exc:
        raise UsageError(f"--effects-from: {exc}") from exc
    for name in modules:
        try:
            mod = importlib.import_module(name)
        except ImportError as exc:
            raise UsageError(f"--effects-from '{name}': no such file or importable module ({exc}).") from exc
        found = {c.name: c for c in vars(mod).values()
                 if isinstance(c, type) and issubclass(c, Effect) and c is not Effect and getattr(c, "name", "")}
        if not found:
            raise UsageError(f"--effects-from '{name}': the module defines no calib.effects.Effect subclass.")
        out.update(found)
    return out


def parse_effects(text: str | None, classes: dict[str, type[Effect]], option: str = "--effects") -> list[Effect]:
    """Effect instances from 'A,B' (empty: none); unknown names are a usage error."""
    if not text:
        return []
    names = [s.strip() for s in text.split(",") if s.strip()]
    if len(set(names)) != len(names):
        raise UsageError(f"{option} '{text}' names an effect twice.")
    try:
        return make_effects(names, classes)
    except EffectLoadError as exc:
        raise UsageError(f"{option} '{text}': {exc}") from exc
