"""`cdpr study`: a Monte-Carlo study of startup plans on the simulated prototype, on Dask.

    cdpr study --plan grid2|grid3|optimal|sequential [...] --runs N --out DIR [--tolerance 3mm]
               [--sim-config FILE] [--effect NAME ...] [--seed S] [--scheduler ADDRESS] [--workers K]
               [--force] [--no-html] [--json]

N simulated startups per plan (seeds S..S+N-1, the same seeds for every plan), each an independent Dask task
on a local cluster (one worker process per core) or on the cluster whose scheduler is at ADDRESS. Each run's
result is saved in DIR as it finishes; running the same study again resumes it (the finished runs are kept).
Prints the table of acquisition/study.py (text, or JSON with ``--json``) and writes DIR/study.html.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
from pathlib import Path

from acquisition.cli.args import claim_output_option
from acquisition.cli.errors import OperationError, UsageError
from acquisition.study import (
    PLANS,
    RunTask,
    StudyConfig,
    StudyCounts,
    StudyError,
    StudyFolder,
    StudyProgress,
    dask_client,
    plan_args,
    run_study,
    study_sim_config,
    study_statistics,
)
from acquisition.study_report import render_study_html, render_table


def register(sub) -> None:
    p = sub.add_parser("study", help="Monte-Carlo study of startup plans on the simulated prototype (Dask)")
    p.add_argument("--plan", nargs="+", choices=PLANS, required=True, help="the plan(s) to study")
    p.add_argument("--runs", type=int, required=True, help="simulated startups per plan")
    p.add_argument("--out", required=True, help="study folder: one JSON file per run, study.html")
    p.add_argument("--tolerance", help="the sequential plan's stop rule: 1-sigma of the initial position, e.g. 3mm")
    p.add_argument("--sim-config", help="simulation configuration YAML of every run (noise, sway, effects)")
    p.add_argument("--effect", nargs="+", default=[], metavar="NAME",
                   help="hidden effect(s) every run simulates, as set in sim_backend/examples/NAME.yaml")
    p.add_argument("--robot", default="irma4u", help="robot description: built-in name or YAML file")
    p.add_argument("--seed", type=int, default=0, help="seed of the first run (default 0)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on the Dask cluster of this scheduler (tcp://host:port)")
    p.add_argument("--workers", type=int, help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--connect-timeout", type=float, default=10.0, help="s to wait for --scheduler (default 10)")
    p.add_argument("--force", action="store_true",
                   help="move aside (kept as NAME.replaced-<time>) what --out holds when it is not this study: "
                   "another study's results or other files; the same study resumes without it")
    p.add_argument("--no-html", action="store_true", help="skip DIR/study.html")
    p.add_argument("--json", action="store_true", help="print the statistics as JSON on stdout")
    p.set_defaults(func=run)


def check_startup_accepts(plans: list[str], tolerance: str | None) -> None:
    """Refuse a plan this checkout's ``cdpr startup`` does not take, before any run starts."""
    from acquisition.cli import build_parser

    for plan in plans:
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                build_parser(("acquisition.cli.startup",)).parse_args(["startup", "--backend", "sim",
                                                                     *plan_args(plan, tolerance)])
        except SystemExit:
            why = (err.getvalue().strip().splitlines() or ["refused"])[-1].removeprefix("cdpr: ").rstrip(".")
            raise UsageError(f"the startup of this checkout does not take the {plan} plan yet ({why}).") from None


class _StudyLines(StudyProgress):
    """A study's progress when stderr is not a terminal: one plain line per tenth of the runs."""

    def __init__(self, total: int):
        from acquisition.cli.progress import Progress

        super().__init__(total, stream=sys.stderr, enabled=False)
        self.lines = Progress(total, "study", "runs", tty=False)

    def advance(self, done: int, failed: int, force: bool = False) -> None:
        self.failed = failed
        self.lines.update(done)


def run(args) -> int:
    from calib.robot import RobotDescriptionError, load_robot

    if args.runs < 1:
        raise UsageError(f"--runs {args.runs} must be at least 1.")
    if args.workers is not None and (args.workers < 1 or args.scheduler):
        raise UsageError(f"--workers {args.workers}: give a positive number of local workers, without --scheduler.")
    if args.connect_timeout <= 0:
        raise UsageError(f"--connect-timeout {args.connect_timeout} must be positive.")
    plans = list(dict.fromkeys(args.plan))
    if args.tolerance is not None and "sequential" not in plans:
        raise UsageError("--tolerance applies to --plan sequential only.")
    if args.tolerance is not None:
        from acquisition.plans import parse_length

        parse_length(args.tolerance, "--tolerance")
    try:
        robot = load_robot(args.robot)
        for plan in plans:
            plan_args(plan, args.tolerance)
        config = StudyConfig(args.robot, study_sim_config(args.sim_config, args.effect, robot.n), args.tolerance)
    except (RobotDescriptionError, StudyError) as exc:
        raise UsageError(str(exc)) from exc
    check_startup_accepts(plans, args.tolerance)
    folder = StudyFolder(args.out)
    seeds = range(args.seed, args.seed + args.runs)
    try:
        folder.prepare(config)
    except StudyError as exc:
        if not args.force:
            raise UsageError(str(exc)) from exc
        # what --out holds (another study's results, other files) is moved aside, never deleted
        claim_output_option(args.out, True, "--out", [args.sim_config] if args.sim_config else [])
        try:
            folder.prepare(config)
        except StudyError as exc2:
            raise UsageError(str(exc2)) from exc2
    tasks = [RunTask(p, s, config) for p in plans for s in seeds if not folder.done(p, s)]
    progress = StudyProgress(len(plans) * len(seeds), stream=sys.stderr)
    if not progress.enabled:  # redirected: plain lines instead of the terminal's bar
        progress = _StudyLines(len(plans) * len(seeds))
    progress.first = len(plans) * len(seeds) - len(tasks)
    t0 = time.perf_counter()
    counts = StudyCounts()
    workers = 0
    if tasks:
        try:
            with dask_client(args.scheduler, args.workers, args.connect_timeout) as client:
                workers = len(client.nthreads())
                counts = run_study(client, folder, tasks, progress)
        except StudyError as exc:
            raise OperationError(str(exc)) from exc
    results = folder.results(plans, seeds)
    stats = study_statistics(results, plans)
    files = {"folder": str(folder.path)}
    if not args.no_html:
        page = Path(folder.path) / "study.html"
        page.write_text(render_study_html(stats, results, config, seeds), encoding="utf-8")
        files["report"] = str(page)
    info = {"runs": {"per_plan": args.runs, "seeds": [seeds.start, seeds.stop - 1], "resumed": progress.first,
                     "ran": counts.ran, "lost": counts.lost,
                     "without_solution": sum(r["status"] != "ok" for r in results)},
            "cluster": {"scheduler": args.scheduler or "local", "workers": workers},
            "wall_s": round(time.perf_counter() - t0, 2), "files": files}
    if args.json:
        sys.stdout.write(json.dumps({"status": "ok", "plans": stats, **info}) + "\n")
    else:
        sys.stdout.write(f"study in {folder.path}: {len(plans)} plan(s) x {args.runs} runs (seeds "
                         f"{seeds.start}..{seeds.stop - 1}); {counts.ran} run now on {workers or 'no'} "
                         f"worker(s) in {info['wall_s']:.0f} s, {progress.first} resumed\n")
        sys.stdout.write(render_table(stats))
        for k, v in files.items():
            sys.stdout.write(f"{k}: {v}\n")
    if counts.lost:
        raise OperationError(f"{counts.lost} run(s) did not come back from the cluster ({counts.lost_reason}); "
                             f"the same command runs them again.")
    return 0
