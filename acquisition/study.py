"""Monte-Carlo study of a startup plan (``cdpr study``): many simulated startups, their errors against the
simulator's truth, the distribution per plan.

Each run is ``cdpr startup --backend sim`` with its own seed (sensor noise, power-on pose, and whatever else
the simulation configuration draws from the seed), run as an independent Dask task. The task starts the
startup in a fresh Python process (``python -m acquisition.study``, :func:`run_startup`): the routine installs its
SIGINT/SIGTERM handlers, which Python allows only in a main thread, and a Dask task runs in a worker's
thread. The process runs the simulated plant in itself rather than in a child of its own: a study keeps
every core busy with runs, where a plant process per run only waits for a core, and its lockstep spends CPU
waiting (measured: 6 runs of grid2 on 2 workers, two loaded cores: 29-36 s of CPU per run with the plant's
process, 7-10 s without, 349 s against 130 s for the study; the same errors to the last digit, as
``sim_backend.backend`` promises). The run folder lives in that process's temporary directory and is
deleted after; the task returns the run's result (:func:`run_result`), which the client writes to the study
folder as soon as it arrives (:class:`StudyFolder`), so an interrupted study resumes where it stopped.

Statistics (:func:`plan_statistics`): the initial-position error |p_est - p_true| (mm), its median,
quartiles, 90th percentile and RMS, against the printed 1-sigma (RMS of sqrt(sx^2 + sy^2 + sz^2), the
predicted RMS of the error), the coverage of the printed 1-sigma and 2-sigma per axis (a calibrated sigma
covers 68.3 % and 95.4 %), and the robot time of the startup (s).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import resource
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from acquisition.plans import STUDY_PLANS, PlanRequest, PlanRequestError, parse_length
from acquisition.progress import ProgressBar
from acquisition.session import StartupRequest
from calib.errors import CdprError

PLANS = STUDY_PLANS
FORMAT = "cdpr-study/1"
RUN_FORMAT = "cdpr-study-run/1"
CONFIG_FILE = "config.json"
RUN_TIMEOUT = 1800.0  # s of wall time one simulated startup may take before the run counts as failed
COVERAGE_EXPECTED = (0.6827, 0.9545)  # a Gaussian's probability within 1 and 2 sigma


class StudyError(CdprError, ValueError):
    """An unusable study request or folder; the message is one sentence."""


@dataclass(frozen=True)
class StudyConfig:
    """What every run of a study shares (what must match to resume a study folder).

    sim_config: the simulation configuration as a YAML mapping (``--sim-config`` with ``--effect`` merged);
    tolerance: the sequential plan's stop rule as ``cdpr startup --tolerance`` takes it (e.g. "3mm")."""

    robot: str = "irma4u"
    sim_config: dict[str, Any] = field(default_factory=dict)
    tolerance: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "robot": self.robot, "sim_config": self.sim_config, "tolerance": self.tolerance}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> StudyConfig:
        return cls(data["robot"], data["sim_config"], data["tolerance"])


@dataclass(frozen=True)
class RunTask:
    """One simulated startup of a study: the plan, the simulator's seed and the shared configuration."""

    plan: str
    seed: int
    config: StudyConfig

    @property
    def name(self) -> str:
        return f"{self.plan}-s{self.seed:05d}"

    def to_dict(self) -> dict[str, Any]:
        return {"plan": self.plan, "seed": self.seed, "config": self.config.to_dict()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunTask:
        return cls(data["plan"], int(data["seed"]), StudyConfig.from_dict(data["config"]))


def plan_args(plan: str, tolerance: str | None = None) -> list[str]:
    """The ``cdpr startup`` options that select ``plan`` (a study's plan name, :data:`acquisition.plans.STUDY_PLANS`);
    raises StudyError for a plan a study does not know."""
    request = plan_request(plan, tolerance)
    if request.kind == "grid":
        return ["--grid", str(request.grid)]
    if request.kind == "optimal":
        return ["--plan", "optimal"]
    return ["--tolerance", str(tolerance)]


def plan_request(plan: str, tolerance: str | None = None) -> PlanRequest:
    """The startup's plan of a study's ``plan`` name, ``tolerance`` a length with its unit (e.g. "3mm").
    Raises StudyError."""
    try:
        return PlanRequest.named(plan, None if tolerance is None else parse_length(tolerance, "--tolerance"))
    except PlanRequestError as exc:
        raise StudyError(str(exc)) from exc


def startup_request(task: RunTask, out: str, truth: str, sim_config: str | None) -> StartupRequest:
    """The startup of one run: the simulated prototype in this process, no HTML report, no progress line."""
    return StartupRequest(backend="sim", plan=plan_request(task.plan, task.config.tolerance), out=Path(out),
                          robot=task.config.robot, seed=task.seed, truth=truth, sim_config=sim_config,
                          sim_plant="inline", html=False, progress=False)


def study_sim_config(path: str | None, effects: Sequence[str], n: int) -> dict[str, Any]:
    """The simulation configuration of a study: the file's mapping (none: the nominal prototype) with each
    named hidden effect set as in its example (``sim_backend/examples/NAME.yaml``); validated for n cables."""
    from sim_backend.config import EFFECTS, SimConfigError, example_path, sim_config_from_dict

    data: dict[str, Any] = {}
    origin = "<nominal>"
    if path is not None:
        p = Path(path)
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except OSError as exc:
            raise StudyError(f"{p}: cannot read the simulation configuration ({exc.strerror}).") from exc
        except yaml.YAMLError as exc:
            raise StudyError(f"{p}: not valid YAML ({str(exc).splitlines()[0]}).") from exc
        if not isinstance(data, dict):
            raise StudyError(f"{p}: the simulation configuration must be a mapping, got {type(data).__name__}.")
        origin = str(p)
    for name in effects:
        if name not in EFFECTS:
            raise StudyError(f"--effect {name!r} is not a hidden effect of the simulator "
                             f"(known: {', '.join(EFFECTS)}).")
        example = yaml.safe_load(example_path(name).read_text())
        data = {**data, "effects": {**(data.get("effects") or {}), name: example["effects"][name]}}
    try:
        sim_config_from_dict(data, n, origin)
    except SimConfigError as exc:
        raise StudyError(str(exc)) from exc
    return data


# ---- one run (on a Dask worker) --------------------------------------------------------------------------


def run_startup(task: RunTask) -> dict[str, Any]:
    """The Dask task of a study: one simulated startup in a fresh process (``python -m acquisition.study``:
    the task as JSON on its stdin, the result of :func:`run_in_this_process` on its stdout), with the run's
    wall time and the CPU time of its process (s, ``wall_s``, ``cpu_s``).

    The process has a session of its own: the operator's Ctrl-C stops the study (the client), not the runs,
    whose safe stops would otherwise be recorded as results; a run cut off from its worker finishes and
    deletes its temporary folder itself."""
    t0, cpu0 = time.perf_counter(), _children_cpu()
    try:
        proc = subprocess.run([sys.executable, "-m", "acquisition.study"], input=json.dumps(task.to_dict()),
                              capture_output=True, text=True, timeout=RUN_TIMEOUT, start_new_session=True)
    except subprocess.TimeoutExpired:
        res = failed_result(task, "failed", f"the startup did not finish within {RUN_TIMEOUT:g} s.")
    else:
        if proc.returncode == 0:
            res = json.loads(proc.stdout)
        else:
            last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
            res = failed_result(task, "failed", f"the run's process ended with status {proc.returncode}: {last}")
    res.update(wall_s=round(time.perf_counter() - t0, 3), cpu_s=round(_children_cpu() - cpu0, 3))
    return res


def _children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children and theirs."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_in_this_process(task: RunTask) -> dict[str, Any]:
    """One run: a simulated startup (:func:`acquisition.session.run_startup`) in a temporary folder (deleted
    after) with the simulated plant in this process (see the module docstring). Returns :func:`run_result` or
    :func:`failed_result`; a refused startup (bad input, exit status 2 at the command line) comes back with
    status ``usage`` and its sentence: it would fail every run, so the study stops on it instead of recording
    it."""
    from acquisition import session

    with tempfile.TemporaryDirectory(prefix=f"cdpr-study-{task.name}-") as tmp:
        sim_file = None
        if task.config.sim_config:
            sim_file = os.path.join(tmp, "sim-config.yaml")
            Path(sim_file).write_text(yaml.safe_dump(task.config.sim_config))
        truth = os.path.join(tmp, "truth.json")
        try:
            outcome = session.run_startup(startup_request(task, os.path.join(tmp, "run"), truth, sim_file))
        except CdprError as exc:
            status = ("usage" if exc.exit_status == 2 else
                      "safe_stop" if getattr(exc, "safe_stop", False) else "failed")
            return failed_result(task, status, str(exc))
        return run_result(task, outcome.summary.to_dict(), outcome.truth)


def run_result(task: RunTask, summary: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    """The result of a finished run: the initial-position error (m) of the solve against the simulator's true
    pose averaged over the reference window (the pose at the reference sample for a truth file without it),
    the printed 1-sigma (m), the robot time (s) and the windows held.

    summary: the startup's summary (``cdpr startup --json``); truth: the simulator's truth (the ``--truth``
    file)."""
    sol = summary["solution"]
    # the solve estimates the pose of the reference window's mean readings: its truth is the pose those mean
    # true readings describe (reading_pose); the pose at the window's middle sample differs by the platform's
    # own motion, and the true pose averaged over the window by that motion's second order (a platform
    # swinging by a millimetre there: -0.35 sigma in z on average, docs/windows.md), kept beside it
    mean = truth.get("window_mean_pose") or truth["initial_pose"]
    true = reading_truth(task.config.robot, sol, truth)
    true = mean if true is None else true
    err = np.asarray(sol["initial_pose"][:3], float) - np.asarray(true[:3], float)
    sigma = np.asarray(sol["initial_pose_sigma"][:3], float)
    return {
        "format": RUN_FORMAT, "plan": task.plan, "seed": task.seed, "status": "ok", "message": "",
        "position_error_m": err.tolist(), "position_sigma_m": sigma.tolist(),
        "mean_pose_error_m": (np.asarray(sol["initial_pose"][:3], float) - np.asarray(mean[:3], float)).tolist(),
        "error_m": float(np.linalg.norm(err)), "sigma_m": float(np.linalg.norm(sigma)),
        "robot_time_s": float(summary["timing"]["acquisition_s"]),
        "windows": summary["windows"], "setpoints": int(summary["setpoints"]), "host": socket.gethostname(),
    }


def reading_pose(robot, poses: np.ndarray, sigma: dict[str, Any], iterations: int = 8) -> np.ndarray:
    """The pose (6,) whose kinematic readings (cable lengths, swivel angles, roll, pitch, yaw; m, rad) are the
    means of those of ``poses`` (k, 6), each reading weighed by the solve's sigma of its channel (``sigma``:
    per channel a list, SI): what a solve from a window's mean readings estimates when the platform moves
    inside the window. Gauss-Newton from the mean pose, central differences (1 um, 1 urad)."""
    from calib.kinematics import convert_euler, inverse_kinematics

    w = np.r_[np.broadcast_to(np.asarray(sigma["length"], float), (robot.n,)),
              np.broadcast_to(np.asarray(sigma["swivel"], float), (robot.n,)),
              np.broadcast_to(np.asarray(sigma["orientation"], float), (3,))]

    def readings(z: np.ndarray) -> np.ndarray:
        kin = inverse_kinematics(robot, z)
        ahrs = convert_euler(z[:, 3:], robot.orientation, robot.ahrs_convention)[0]
        return np.c_[kin.lengths, kin.swivel, ahrs] / w

    poses = np.asarray(poses, float)
    target = readings(poses).mean(axis=0)
    z = poses.mean(axis=0)
    h = 1e-6 * np.eye(6)
    for _ in range(iterations):
        r = readings(np.vstack([z, z + h, z - h]))
        J = (r[1:7] - r[7:]).T / 2e-6
        step = np.linalg.lstsq(J, target - r[0], rcond=None)[0]
        z = z + step
        if np.max(np.abs(step)) < 1e-12:
            break
    return z


def reading_truth(robot_name: str, solution: dict[str, Any], truth: dict[str, Any]) -> list[float] | None:
    """:func:`reading_pose` of the true poses of the solve's reference window (truth.json ``poses``, the
    solution's ``windows`` and ``reference_sample``); None when the truth or the solution lacks them."""
    from calib.robot import load_robot

    poses, sample = truth.get("poses"), solution.get("reference_sample")
    span = next(((a, b) for a, b in solution.get("windows") or [] if sample is not None and a <= sample <= b), None)
    if not poses or span is None or not isinstance(solution.get("noise"), dict):
        return None
    z = reading_pose(load_robot(robot_name), np.asarray(poses, float)[span[0]:span[1] + 1], solution["noise"])
    return [float(v) for v in z]


def failed_result(task: RunTask, status: str, message: str) -> dict[str, Any]:
    """The result of a run that ended without a solution: ``safe_stop``, ``failed`` or ``usage``."""
    return {"format": RUN_FORMAT, "plan": task.plan, "seed": task.seed, "status": status, "message": message,
            "position_error_m": None, "position_sigma_m": None, "mean_pose_error_m": None, "error_m": None,
            "sigma_m": None,
            "robot_time_s": None, "windows": [], "setpoints": None, "host": socket.gethostname()}


# ---- the study folder ------------------------------------------------------------------------------------


class StudyFolder:
    """The study's folder: its configuration (config.json) and one JSON file per finished run.

    A folder holding the results of another configuration, or anything else, is refused (`cdpr study --force`
    moves it aside first, as every command does, never deleting); the same configuration resumes (its
    finished runs are kept and not run again)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def result_path(self, plan: str, seed: int) -> Path:
        return self.path / f"run-{plan}-s{seed:05d}.json"

    def prepare(self, config: StudyConfig) -> None:
        """Create the folder, or check that it holds this configuration. Raises StudyError."""
        p = self.path
        if p.exists() and not p.is_dir():
            raise StudyError(f"--out {p} exists and is not a folder.")
        cfg_file = p / CONFIG_FILE
        want = config.to_dict()
        if cfg_file.exists():
            try:
                have = json.loads(cfg_file.read_text())
            except (OSError, ValueError) as exc:
                raise StudyError(f"{cfg_file}: not a study configuration ({exc}).") from exc
            if have == want:
                return
            key = next((k for k in want if have.get(k) != want[k]), "format")
            raise StudyError(f"{p} holds the results of another study ({key} {have.get(key)!r} there, "
                             f"{want[key]!r} now): give another --out, or --force to move them aside.")
        if p.is_dir() and any(p.iterdir()):
            raise StudyError(f"--out {p} exists and is not a study folder: give another --out, or --force to "
                             f"move it aside.")
        p.mkdir(parents=True, exist_ok=True)
        _write_json(cfg_file, want)

    def done(self, plan: str, seed: int) -> bool:
        return self.result_path(plan, seed).exists()

    def write(self, result: dict[str, Any]) -> Path:
        """Save one run's result (atomically: a study cut at any moment leaves whole files only)."""
        return _write_json(self.result_path(result["plan"], int(result["seed"])), result)

    def results(self, plans: Sequence[str], seeds: Sequence[int]) -> list[dict[str, Any]]:
        """The saved results of these plans and seeds (those that exist)."""
        out = []
        for plan in plans:
            for seed in seeds:
                f = self.result_path(plan, seed)
                if f.exists():
                    out.append(json.loads(f.read_text()))
        return out


def _write_json(path: Path, data: Any) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data) + "\n")
    tmp.replace(path)
    return path


# ---- running on Dask -------------------------------------------------------------------------------------


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, timeout: float = 10.0) -> Iterator[Any]:
    """A ``distributed.Client`` on the scheduler at ``scheduler``, or on a local cluster of ``workers``
    single-threaded worker processes (default: one per core this process may use)."""
    import logging

    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise StudyError("cdpr study needs dask and distributed: pip install 'cdpr[study]'.") from exc

    if scheduler:
        try:
            client = Client(scheduler, timeout=timeout)
        except ValueError as exc:  # not an address
            raise StudyError(f"--scheduler {scheduler!r} is not a Dask scheduler address ({exc}).") from exc
        except (OSError, TimeoutError) as exc:
            raise StudyError(f"cannot reach the Dask scheduler at {scheduler} within {timeout:g} s.") from exc
        with client:
            yield client
        return
    n = workers or len(os.sched_getaffinity(0))
    # dashboard_address ":0": its HTTP server (which runs even without a dashboard) on a free port, not 8787
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        yield client


class StudyProgress(ProgressBar):
    """The progress line of a study: runs done of the total, failures, and the wall time left."""

    def __init__(self, total: int, stream=None, enabled: bool | None = None):
        super().__init__(total, stream=stream, enabled=enabled)
        self.t0 = time.monotonic()
        self.first = 0  # runs done before this session (resumed)
        self.failed = 0

    def line(self, elapsed: float, phase: str, setpoint: int, count: int) -> str:
        done = int(elapsed)
        frac = min(done / self.total, 1.0)
        full = int(round(frac * self.width))
        ran = done - self.first
        left = (time.monotonic() - self.t0) / ran * (self.total - done) if ran else math.nan
        eta = f"~{left:5.0f} s left" if math.isfinite(left) else "~    ? s left"
        return f"[{'#' * full}{'.' * (self.width - full)}] {done}/{int(self.total)} runs  {self.failed} failed  {eta}"

    def advance(self, done: int, failed: int, force: bool = False) -> None:
        self.failed = failed
        self.update(done, "runs", -1, int(self.total), force=force)


@dataclass
class StudyCounts:
    """What :func:`run_study` did: runs saved now, of which without a solution, and runs the cluster lost (a
    worker died: not a result, so not saved; the next call runs them again), with the first reason."""

    ran: int = 0
    failed: int = 0
    lost: int = 0
    lost_reason: str = ""


def run_study(client, folder: StudyFolder, tasks: Sequence[RunTask], progress: StudyProgress | None = None
              ) -> StudyCounts:
    """Submit the tasks (runs not yet in ``folder``) and save each result as it arrives. A usage error of a
    run stops the study with its sentence (:class:`StudyError`)."""
    from distributed import as_completed

    futures = [client.submit(run_startup, t, key=f"cdpr-study-{t.name}-{os.getpid()}-{time.time_ns()}", pure=False)
               for t in tasks]
    counts = StudyCounts()
    done0 = progress.first if progress is not None else 0
    try:
        for fut in as_completed(futures):
            try:
                res = fut.result()
            except Exception as exc:  # the task did not come back (a worker died): run it again next time
                counts.lost += 1
                counts.lost_reason = counts.lost_reason or f"{type(exc).__name__}: {str(exc).rstrip('.')}"
                continue
            if res["status"] == "usage":
                raise StudyError(f"cdpr startup refused the {res['plan']} plan: {res['message'].rstrip('.')}.")
            folder.write(res)
            counts.ran += 1
            counts.failed += res["status"] != "ok"
            if progress is not None:
                progress.advance(done0 + counts.ran, counts.failed)
    finally:
        client.cancel(futures)
        if progress is not None:
            progress.advance(done0 + counts.ran, counts.failed, force=True)
            progress.close()
    return counts


# ---- statistics and reports ------------------------------------------------------------------------------


def _quantiles(x: np.ndarray) -> dict[str, float] | None:
    if not len(x):
        return None
    q1, med, q3, p90 = np.percentile(x, [25, 50, 75, 90])
    return {"median": float(med), "q1": float(q1), "q3": float(q3), "p90": float(p90),
            "rms": float(np.sqrt(np.mean(x**2)))}


def plan_statistics(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Statistics of one plan's runs: counts, position error (mm), printed sigma (mm), robot time (s),
    coverage of the printed 1-sigma and 2-sigma per axis (pooled over x, y, z, and axis by axis in
    ``axes`` with each axis's rms(error / sigma))."""
    ok = [r for r in results if r["status"] == "ok"]
    err = np.array([r["position_error_m"] for r in ok], float).reshape(-1, 3) * 1000.0
    sig = np.array([r["position_sigma_m"] for r in ok], float).reshape(-1, 3) * 1000.0
    norm = np.linalg.norm(err, axis=1)
    pred = np.linalg.norm(sig, axis=1)
    stats: dict[str, Any] = {
        "runs": len(results), "ok": len(ok),
        "safe_stops": sum(r["status"] == "safe_stop" for r in results),
        "failed": sum(r["status"] == "failed" for r in results),
        "error_mm": _quantiles(norm), "sigma_mm": _quantiles(pred),
        "robot_time_s": _quantiles(np.array([r["robot_time_s"] for r in ok], float)),
        "rms_error_over_sigma": None, "coverage_1sigma": None, "coverage_2sigma": None,
        "axes": None,  # per axis x, y, z: rms(error / sigma) and the coverage of the 1-sigma and 2-sigma
    }
    if len(ok):
        stats["rms_error_over_sigma"] = float(np.sqrt(np.mean(norm**2) / np.mean(pred**2)))
        ratio = np.abs(err) / sig
        stats["coverage_1sigma"] = float(np.mean(ratio <= 1.0))
        stats["coverage_2sigma"] = float(np.mean(ratio <= 2.0))
        stats["axes"] = {"rms_error_over_sigma": np.sqrt(np.mean(ratio**2, axis=0)).tolist(),
                         "coverage_1sigma": np.mean(ratio <= 1.0, axis=0).tolist(),
                         "coverage_2sigma": np.mean(ratio <= 2.0, axis=0).tolist()}
    return stats


def study_statistics(results: Sequence[dict[str, Any]], plans: Sequence[str]) -> dict[str, dict[str, Any]]:
    """:func:`plan_statistics` of each plan."""
    return {p: plan_statistics([r for r in results if r["plan"] == p]) for p in plans}


if __name__ == "__main__":  # one run of a study: the process run_startup starts
    sys.stdout.write(json.dumps(run_in_this_process(RunTask.from_dict(json.load(sys.stdin)))) + "\n")
