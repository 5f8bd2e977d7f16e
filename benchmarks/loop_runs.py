"""Full simulated startups for the plan benchmarks (issue 19; not collected by pytest): one startup per plan
and seed on the simulated prototype with realistic noise (sim_backend/examples/rigid_sway.yaml: load cells
1 N, encoders 0.2 mm, AHRS 0.02 deg, a slow sway; rigid cables, see docs/planning.md), its initial-position
error against the simulator's pose averaged over the reference window (what a window-mean solve estimates)
with the solve of ``cdpr solve --noise estimate`` (the run's own window-mean noise and the devices' datasheet
errors), its printed 1-sigma and its robot time. Results are cached per run in ``cache`` (JSON), so that
bench_sequential.py and bench_plans.py share the grid's runs.
"""

from __future__ import annotations

import json
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

CONFIG = "rigid_sway"


def one(plan: str, seed: int, tolerance: float | None, step: float) -> dict:
    """One simulated startup and its estimate-noise solve: error and 1-sigma (m), robot time (s), poses."""
    from acquisition.runlog import read_run
    from acquisition.session import simulated_startup
    from calib.robot import load_robot
    from calib.selfcal import solve
    from sim_backend.config import example_path

    robot = load_robot("irma4u")
    with tempfile.TemporaryDirectory() as tmp:
        out = simulated_startup(Path(tmp) / "run", plan, tolerance=tolerance, seed=seed, step=step,
                                sim_config=str(example_path(CONFIG)))
        run = read_run(out["run"])
        sol = solve(robot, run, noise="estimate")
    truth = np.asarray(out["truth_window_mean"] or out["truth"], float)
    seq = run.meta.get("sequential") or {}
    return {"plan": plan, "seed": seed, "tolerance": tolerance,
            "error_m": float(np.linalg.norm(sol.initial_pose[:3] - truth[:3])),
            "sigma_m": float(np.sqrt(max(np.trace(sol.covariance[:3, :3]), 0.0))),
            "robot_time_s": float(out["timing"]["acquisition_s"]), "poses": int(out["setpoints"]),
            "online_sigma_m": [w["position_sigma_m"] for w in seq.get("windows", [])], "stop": seq.get("stop"),
            "message": out.get("message"),
            "setpoints": run.setpoints.tolist(), "ideal_poses": run.ideal_poses.tolist(),
            "noise": sol.noise}  # the run's window-mean sigmas per channel (calib.design.LOOP_NOISE's source)


def _key(plan: str, seed: int, tolerance: float | None) -> str:
    return f"{plan}-{seed}" + ("" if tolerance is None else f"-{1e6 * tolerance:.0f}um")


def runs(plan: str, seeds: int, tolerance: float | None = None, step: float = 0.1, cache: str | None = None,
         workers: int = 2) -> list[dict]:
    """The results of ``seeds`` startups of ``plan`` (seeds 0..seeds-1), from the cache where it has them."""
    folder = Path(cache or os.path.join(tempfile.gettempdir(), "cdpr-bench-loop"))
    folder.mkdir(parents=True, exist_ok=True)
    def cached(s: int) -> bool:  # results from before the noise was recorded are run again
        f = folder / f"{_key(plan, s, tolerance)}.json"
        return f.is_file() and "noise" in json.loads(f.read_text())

    todo = [s for s in range(seeds) if not cached(s)]
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        for res in pool.map(one, [plan] * len(todo), todo, [tolerance] * len(todo), [step] * len(todo)):
            (folder / f"{_key(plan, res['seed'], tolerance)}.json").write_text(json.dumps(res))
    return [json.loads((folder / f"{_key(plan, s, tolerance)}.json").read_text()) for s in range(seeds)]


def cached_runs(plan: str, seeds: int, tolerance: float | None = None, cache: str | None = None) -> list[dict]:
    """The cached results of seeds 0..seeds-1 of ``plan``, or [] unless all of them are in the cache."""
    folder = Path(cache or os.path.join(tempfile.gettempdir(), "cdpr-bench-loop"))
    files = [folder / f"{_key(plan, s, tolerance)}.json" for s in range(seeds)]
    if not all(f.is_file() for f in files):
        return []
    return [json.loads(f.read_text()) for f in files]
