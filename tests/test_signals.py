"""SIGTERM and SIGINT at several moments of `cdpr startup --backend sim`, from the first instant its Python
code runs: always one sentence and exit status 1; once the run folder exists, a run that reads back."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from acquisition.runlog import read_run

CDPR = [sys.executable, "-c", "import sys; from acquisition.cli import main; sys.exit(main())"]


def _caught(pid: int) -> bool:
    """SIGTERM has a handler in the process (bit 15 of SigCgt): cdpr's main has begun."""
    status = Path(f"/proc/{pid}/status").read_text()
    return bool(int(next(x for x in status.splitlines() if x.startswith("SigCgt:")).split()[1], 16)
                & (1 << (signal.SIGTERM - 1)))


def _logged(out: Path) -> bool:
    f = out / "samples.csv"
    return f.is_file() and f.read_bytes().count(b"\n") > 60


def _after(seconds: float):
    """A moment ``seconds`` after cdpr's main began: loading, planning, connecting, zeroing (the load decides)."""
    state = {}

    def reached(proc, out) -> bool:
        if "t0" not in state and _caught(proc.pid):
            state["t0"] = time.monotonic()
        return "t0" in state and time.monotonic() - state["t0"] >= seconds

    return reached


MOMENTS = {
    "first_instant": lambda: lambda proc, out: _caught(proc.pid),
    "after_1s": lambda: _after(1.0),
    "after_3s": lambda: _after(3.0),
    "logging": lambda: lambda proc, out: _logged(out),
}


@pytest.mark.parametrize(
    "moment, sig",
    [("first_instant", signal.SIGTERM), ("first_instant", signal.SIGINT), ("after_1s", signal.SIGTERM),
     ("after_3s", signal.SIGINT), ("logging", signal.SIGTERM)],
)
def test_a_signal_at_any_moment_gives_one_sentence_and_a_readable_run(tmp_path, moment, sig):
    out = tmp_path / "run"
    # the timed moments pace the simulated prototype in real time: unpaced, an idle machine runs the whole
    # 88 s startup in about 3 s, and "3 s after main began" could fall after the command had ended
    paced = ["--realtime"] if moment.startswith("after_") else []
    proc = subprocess.Popen([*CDPR, "startup", "--backend", "sim", "--grid", "2", "--out", str(out), *paced],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    reached = MOMENTS[moment]()
    deadline = time.monotonic() + 600
    while proc.poll() is None and time.monotonic() < deadline and not reached(proc, out):
        time.sleep(0.005)
    assert proc.poll() is None, "the startup ended before the moment was reached"
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 1 and stderr.count("\n") == 1 and "Traceback" not in stderr, stderr
    name = signal.Signals(sig).name
    sentences = {  # what each phase says: before the command, before the acquisition, during it
        "first_instant": [f"cdpr: interrupted by the operator ({name}) before the command started; nothing was "
                          "written.\n"],
        "logging": [f"cdpr: safe stop: stopped by the operator ({name}) (run log: {out}).\n"],
    }.get(moment, [f"cdpr: interrupted by the operator ({name}) before the command started; nothing was written.\n",
                   f"cdpr: stopped by {name} before the acquisition started; no run was written.\n",
                   f"cdpr: safe stop: stopped by the operator ({name}).\n",
                   f"cdpr: safe stop: stopped by the operator ({name}) (run log: {out}).\n"])
    assert stderr in sentences, stderr
    if "nothing was written" in stderr or "no run was written" in stderr:
        assert not out.exists()
    if (out / "run.yaml").exists():
        run = read_run(out)
        assert [e["kind"] for e in run.events] == ["operator"]
        if moment == "logging":
            assert len(run) >= 60
