"""The learned robot model: the effects a diagnosis kept, their values and 1-sigma, and where they come from
(issue 28, what to build 4; format in docs/robot-model.md).

``cdpr diagnose RUN... --model-out MODEL.yaml`` writes it (:func:`model_document`, :func:`write_model`);
``cdpr solve``, ``cdpr startup`` and ``cdpr diagnose`` read it with ``--model MODEL.yaml``
(:func:`read_model`) and use every effect as a prior: the effect's parameters start at the learned values,
with a Gaussian prior of the learned 1-sigma (:func:`prior_effects`). :func:`solve_with_model` is the solve of
one run with those priors and the run's own unknowns (the joint fit of :mod:`calib.multirun` on one run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.effects import Effect
from calib.errors import CdprError
from calib.multirun import JointFit, Learned, RunFit, fit_runs
from calib.spread import between_run_sd, per_run_fits, spread

FORMAT = "cdpr-robot-model"
VERSION = 1


class ModelFileError(CdprError, ValueError):
    """A model file that cannot be used (the message names the file, the field and the value)."""


@dataclass
class LearnedEffect:
    """One effect of a model: its name, parameter values and 1-sigma by parameter name (the effect's own
    parameters, ``ParamSpec`` names and units)."""

    name: str
    values: dict[str, float]
    sigma: dict[str, float]


@dataclass
class RobotModel:
    """A learned robot model: the effects, the runs it was learned from (with their weights and own
    unknowns) and free-form provenance."""

    effects: list[LearnedEffect]
    runs: list[dict[str, Any]] = field(default_factory=list)
    selection: dict[str, Any] = field(default_factory=dict)
    robot: str = ""

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]


def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def learned_of(fit: JointFit, skip: tuple[str, ...] = ()) -> list[LearnedEffect]:
    """The shared effects of a joint fit as learned effects (inner parameters of restricted ones)."""
    robot = fit.runs[0].rows.robot
    out, q = [], 0
    sig = fit.shared_sigmas()
    for e in fit.shared:
        nq = len(e.params(robot))
        inner = getattr(e, "inner", e)
        vals = e.full_values(robot, fit.values[q:q + nq]) if hasattr(e, "full_values") else fit.values[q:q + nq]
        names = [s.name for s in inner.params(robot)]
        if e.name not in skip:
            out.append(LearnedEffect(e.name, dict(zip(names, map(float, vals), strict=True)),
                                     {k: float(sig[e.name].get(k, 0.0)) for k in names}))
        q += nq
    return out


def run_summary(rf: RunFit, path: str | None = None) -> dict[str, Any]:
    """What a model file keeps of a run it was learned from: name, path, the weights (per channel group),
    the run's own unknowns (initial pose, yaw drift rate) and its rms residual per channel."""
    p = rf.params()
    drift = p.get("ahrs_yaw_drift", {}).get("deg_per_hour")
    return {"name": rf.name, "path": path, "initial_pose": [float(v) for v in rf.theta[:6]],
            "yaw_drift_deg_per_hour": drift,
            "weights": {c: [float(v) for v in s] for c, s in rf.sigma.items()},
            "rms": rf.rms()}


def between_runs(fit: JointFit) -> dict[str, dict[str, Any]]:
    """Per shared effect: the between-run 1-sigma of each parameter (``tau``, DerSimonian-Laird over the
    runs' own fits, :func:`calib.spread.between_run_sd`) and the runs' consistency test (chi2, dof, p of
    :func:`calib.spread.spread` on its parameters). Empty with one run."""
    if len(fit.runs) < 2:
        return {}
    fits = per_run_fits(fit)
    own = [{e.name: e for e in learned_of(f)} for f in fits]
    robot = fit.runs[0].rows.robot
    out, q = {}, 0
    for e in fit.shared:
        nq = len(e.params(robot))
        sp = spread(fit, range(q, q + nq), fits)
        names = list(own[0][e.name].values)
        x = np.array([[o[e.name].values[k] for k in names] for o in own])
        var = np.array([[o[e.name].sigma[k] ** 2 for k in names] for o in own])
        out[e.name] = {"tau": dict(zip(names, map(float, between_run_sd(x, var)), strict=True)),
                       "consistency": {"chi2": sp.chi2, "dof": sp.dof, "p": sp.p}}
        q += nq
    return out


def model_document(fit: JointFit, paths: list[str] | None = None, selection: dict[str, Any] | None = None,
                   robot: str = "") -> dict[str, Any]:
    """The YAML document of a learned model (docs/robot-model.md). With several runs each parameter's
    ``sigma`` is the 1-sigma of a new run's value: the joint fit's (``sigma_mean``) and the between-run
    spread (``between_runs``) in quadrature."""
    eff = learned_of(fit)
    reports = fit.shared_params()
    spreads = between_runs(fit)
    docs = []
    for e in eff:
        d = {"name": e.name, "values": e.values, "sigma": e.sigma, "report": reports.get(e.name, {})}
        if e.name in spreads:
            tau = spreads[e.name]["tau"]
            d["sigma"] = {k: math.hypot(v, tau[k]) for k, v in e.sigma.items()}
            d.update(sigma_mean=e.sigma, between_runs=tau, consistency=spreads[e.name]["consistency"])
        docs.append(d)
    return _plain({
        "format": FORMAT,
        "version": VERSION,
        "robot": robot,
        "effects": docs,
        "runs": [run_summary(rf, None if paths is None else paths[i]) for i, rf in enumerate(fit.runs)],
        "fit": fit.convergence(),
        "selection": selection or {},
    })


def write_model(path: Path, doc: dict[str, Any], force: bool = False) -> None:
    """Write a model document; an existing file is refused unless ``force``."""
    path = Path(path)
    if path.exists() and not force:
        raise FileExistsError(f"{path}: exists; give --force to overwrite it.")
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def read_model(path: Path) -> RobotModel:
    """Read a model file; bad content raises ModelFileError naming the file, field and value."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model file ({exc.strerror}).") from exc
    except yaml.YAMLError as exc:
        raise ModelFileError(f"{path}: not YAML ({exc}).") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ModelFileError(f"{path}: field 'format' is {got!r}, expected {FORMAT!r}.")
    if doc.get("version") != VERSION:
        raise ModelFileError(f"{path}: field 'version' is {doc.get('version')!r}, expected {VERSION}.")
    effects = []
    for i, e in enumerate(doc.get("effects") or []):
        if not isinstance(e, dict) or not isinstance(e.get("name"), str):
            raise ModelFileError(f"{path}: effects[{i}] has no 'name'.")
        vals, sig = e.get("values") or {}, e.get("sigma") or {}
        for key, table in (("values", vals), ("sigma", sig)):
            for k, v in table.items():
                if not isinstance(v, (int, float)) or not math.isfinite(float(v)) or (key == "sigma" and v < 0):
                    raise ModelFileError(f"{path}: effects[{i}] ({e['name']}) {key}.{k} is {v!r}, not a "
                                         f"{'non-negative ' if key == 'sigma' else ''}finite number.")
        effects.append(LearnedEffect(e["name"], {k: float(v) for k, v in vals.items()},
                                     {k: float(v) for k, v in sig.items()}))
    return RobotModel(effects, list(doc.get("runs") or []), dict(doc.get("selection") or {}),
                      str(doc.get("robot") or ""))


def prior_effects(model: RobotModel, robot, classes: dict[str, type[Effect]], path: Path | str = "model",
                  frozen: bool = False) -> list[Effect]:
    """The model's effects as priors: each effect's parameters at the learned values with a Gaussian prior
    of the learned 1-sigma (``frozen``: held at them)."""
    out: list[Effect] = []
    for e in model.effects:
        if e.name not in classes:
            raise ModelFileError(f"{path}: effect '{e.name}' is not in the library (known: {', '.join(classes)}).")
        inner = classes[e.name]()
        specs = inner.params(robot)
        missing = [s.name for s in specs if s.name not in e.values]
        if missing:
            raise ModelFileError(f"{path}: effect '{e.name}' lacks the values of {', '.join(missing)}.")
        vals = np.array([e.values[s.name] for s in specs])
        sd = None if frozen else np.array([e.sigma.get(s.name, 0.0) for s in specs])
        out.append(Learned(inner, robot, vals, sd))
    return out


def solve_with_model(rows, effects: list[Effect], name: str = "run") -> JointFit:
    """One run solved with a model's effects as priors and its own unknowns refitted (initial pose, poses,
    device errors, reference noise, yaw drift rate), weights by variance components: the fit of one run
    (``runs[0]``) and whether it converged."""
    return fit_runs([(name, rows)], effects)
