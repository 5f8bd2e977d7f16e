"""How fast the `cdpr` command answers (not collected by pytest).

    python benchmarks/bench_cli_startup_time.py [--data DIR] [--repeat R] [--work DIR]

Wall time of whole processes, median of R runs (default 5), all in this one run:
- `cdpr --version` against `python -c "import numpy"`: target at most 1.5x;
- `cdpr solve RUN` of sc_8_final (imported first with `cdpr import irma`) against
  `python -c "import numpy, scipy.linalg, yaml"`: target at most 1.5x.
Every process is started with this interpreter (the `cdpr` console script beside it, or the `cdpr` on PATH),
so the baselines and the commands pay the same interpreter start. Exits 1 on a miss.
"""

from __future__ import annotations

import argparse
import os
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


def wall(cmd: list[str], repeat: int) -> float:
    """Median wall time of ``cmd``, s (a failed command stops the benchmark)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        times.append(time.perf_counter() - t0)
        if proc.returncode:
            sys.exit(f"bench_cli_startup_time: {' '.join(cmd)} failed: {proc.stderr.strip()}")
    return statistics.median(times)


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
        for name, cmd, base_name, base_code in cases:
            base = wall([sys.executable, "-c", base_code], a.repeat)
            t = wall(cmd, a.repeat)
            ok = t <= RATIO * base
            missed += not ok
            print(f"{name:<24} {t * 1e3:7.0f} ms  {base_name}: {base * 1e3:6.0f} ms  ratio {t / base:5.2f} "
                  f"(target <= {RATIO})  {'ok' if ok else 'MISS'}")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
