"""How fast the `cdpr` command answers (not collected by pytest).

    python benchmarks/bench_cli_startup_time.py [--data DIR] [--repeat R] [--work DIR]

Wall time of whole processes, median of R runs (default 5), all in this one run, and beside it their CPU time
(user + sys, median; the load of a shared machine disturbs it less) and the load average before and after:
- `cdpr --version` against `python -c "import numpy"`: target at most 1.5x;
- `cdpr solve RUN` of sc_8_final (imported first with `cdpr import irma`) against
  `python -c "import numpy, scipy.linalg, yaml"`: target at most 1.5x.
Every process is started with this interpreter (the `cdpr` console script beside it, or the `cdpr` on PATH),
so the baselines and the commands pay the same interpreter start. Exits 1 on a miss.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RATIO = 1.5


def cdpr_command() -> list[str]:
    """How to start the `cdpr` console script with this interpreter."""
    beside = Path(sys.executable).with_name("cdpr")
    script = beside if beside.exists() else shutil.which("cdpr")
    if script is None:
        sys.exit("bench_cli_startup_time: no `cdpr` console script (pip install -e .)")
    return [sys.executable, str(script)]


def measure(cmd: list[str], repeat: int) -> tuple[float, float]:
    """Median wall time and median CPU time (user + sys) of ``cmd``, s (a failed command stops the benchmark).
    The CPU time is what a shared machine's load disturbs least."""
    walls, cpus = [], []
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        walls.append(time.perf_counter() - t0)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        if proc.returncode:
            sys.exit(f"bench_cli_startup_time: {' '.join(cmd)} failed: {proc.stderr.strip()}")
    return statistics.median(walls), statistics.median(cpus)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("CDPR_DATA", "../shared/data/irma4u")))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--work", type=Path, help="folder for the imported run (default: a temporary one)")
    a = ap.parse_args()
    cdpr = cdpr_command()
    with tempfile.TemporaryDirectory() as tmp:
        run = (a.work or Path(tmp)) / "sc8f"
        if not run.exists():
            subprocess.run([*cdpr, "import", "irma", str(a.data / "sc_8_final_parsed.mat"), "--targets",
                            str(a.data / "sc_control_target_8_final.mat"), "-o", str(run)],
                           check=True, stdout=subprocess.DEVNULL)
        cases = [
            ("cdpr --version", [*cdpr, "--version"], 'python -c "import numpy"', "import numpy"),
            ("cdpr solve sc_8_final", [*cdpr, "solve", str(run)], 'python -c "import numpy, scipy.linalg, yaml"',
             "import numpy, scipy.linalg, yaml"),
        ]
        missed = 0
        print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} (1, 5, 15 min), {os.cpu_count()} cores")
        for name, cmd, base_name, base_code in cases:
            base, base_cpu = measure([sys.executable, "-c", base_code], a.repeat)
            t, cpu = measure(cmd, a.repeat)
            ok = t <= RATIO * base
            missed += not ok
            print(f"{name:<24} {t * 1e3:7.0f} ms  {base_name}: {base * 1e3:6.0f} ms  ratio {t / base:5.2f} "
                  f"(target <= {RATIO})  {'ok' if ok else 'MISS'}")
            print(f"{'':<24} CPU {cpu * 1e3:4.0f} ms  {'':<{len(base_name) - 4}}CPU {base_cpu * 1e3:4.0f} ms  "
                  f"ratio {cpu / base_cpu:5.2f}")
        print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} at the end")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
