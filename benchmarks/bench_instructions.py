"""Instructions the full simulated startup executes, counted by valgrind: a speed figure the VM's drift leaves alone.

    python benchmarks/bench_instructions.py            # 'cdpr startup --backend sim --grid 2 --no-html'
    python benchmarks/bench_instructions.py --grid 3   # 27 poses

The wall-time benchmark (bench_sim.py) moves by up to 1.6x with the machine's momentary speed, which hides
a change of a few percent. This one runs the same startup with the plant in this process (one process to
count: the physics, the CAN nodes, the drivers and the routine) under valgrind's cachegrind without its
cache model (``--cache-sim=no``, about 30x slower: 2 minutes for --grid 2) and prints the instructions
executed, in all and per control tick. Two commits compared this way differ by what they execute, within
about 0.1 % from run to run. Needs valgrind on the PATH.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

_RUN = r"""
import sys, tempfile
from pathlib import Path
import sim_backend.backend as backend
backend.child_process_possible = lambda: False  # one process: the plant is counted with the rest
from acquisition.cli import main
with tempfile.TemporaryDirectory() as tmp:
    status = main(["startup", "--backend", "sim", "--grid", sys.argv[1], "--out", str(Path(tmp) / "run"),
                   "--no-html", "--json"])
print("STATUS", status)
"""


def count(grid: int) -> tuple[int, float]:
    """(instructions executed by the whole startup, robot time s) under cachegrind."""
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        raise SystemExit("bench_instructions: valgrind is not on the PATH (Debian: apt install valgrind).")
    root = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(
            [valgrind, "--tool=cachegrind", "--cache-sim=no", f"--cachegrind-out-file={Path(tmp) / 'cg.out'}",
             sys.executable, "-c", _RUN, str(grid)],
            capture_output=True, text=True, cwd=tmp, env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"},
        )
    refs = re.search(r"I\s+refs:\s+([\d,]+)", out.stderr)
    result = re.search(r'"acquisition_s": ([\d.]+)', out.stdout)
    if out.returncode != 0 or refs is None or result is None or "STATUS 0" not in out.stdout:
        raise SystemExit(f"bench_instructions: the startup failed under valgrind:\n{out.stdout[-2000:]}\n"
                         f"{out.stderr[-2000:]}")
    return int(refs.group(1).replace(",", "")), float(result.group(1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=2, help="calibration grid points per axis (default 2)")
    args = ap.parse_args(argv)
    instructions, robot_time = count(args.grid)
    ticks = robot_time * 200.0  # the default control rate
    print(f"cdpr startup --backend sim --grid {args.grid} --no-html, plant in one process: "
          f"{instructions / 1e9:.3f} G instructions for {robot_time:.1f} s of robot time "
          f"({instructions / ticks / 1e3:.0f} k per 5 ms tick, setup and solve included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
