"""The startup report from arrays: text summary, offsets file, self-contained HTML, progress line."""

import base64
import datetime as dt
import io
import math
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from acquisition.progress import ProgressBar
from acquisition.report import (
    ReportRenderer,
    StartupSummary,
    offsets_document,
    read_offsets,
    render_html,
    render_text,
    write_html,
    write_offsets,
)

SOLUTION = {
    "method": "tlse",
    "initial_pose": [0.0012, -0.0021, 1.0651, 0.0011, -0.0007, 0.0031],
    "initial_pose_sigma": [0.0004, 0.0005, 0.0002, 0.0001, 0.0001, 0.0003],
    "reference_sample": 10,
    "sensor_offsets": {"length": [2.0, 2.01, 2.02, 2.03], "swivel": [0.5, -0.5, 0.5, -0.5], "yaw": 0.0031},
    "chi2": 12.5, "dof": 40,
    "residuals": {"tension": {"rms": 0.31, "rms_normalized": 0.031}, "length": {"rms": 1e-4, "rms_normalized": 0.01}},
}


def summary():
    return StartupSummary("ok", "RUN", "equilibrium", 9, solution=SOLUTION, windows=[(0, 19), (60, 79)],
                          timing={"acquisition_s": 120.0, "solve_s": 0.02, "control_p99_ms": 0.11})


def test_text_summary_shows_pose_in_mm_and_degrees_with_sigma():
    text = render_text(summary())
    assert "z       1065.100 +- 0.200 mm" in text
    assert f"yaw   {math.degrees(0.0031):10.3f} +- {math.degrees(0.0003):.3f} deg" in text
    assert "  tension             0.31 N        0.031" in text  # the unit beside the rms, not after rms/noise
    assert "[0, 19], [60, 79]" in text
    assert "  time: acquisition_s 120.00 s, solve_s 0.02 s, control_p99_ms 0.11 ms" in text


def test_text_summary_says_when_the_model_misses_its_noise():
    """chi2 12.5 on 40 dof says nothing of a misfit; 4000 on 40 says the bounds are 10 times too narrow."""
    assert "chi2 above its band" not in render_text(summary())
    bad = StartupSummary("ok", "RUN", "equilibrium", 9, solution=SOLUTION | {"chi2": 4000.0}, windows=[(0, 19)])
    text = render_text(bad)
    assert "chi2 above its band" in text and "sqrt(chi2/dof) = 10 times" in text and text.count("chi2 above") == 1


def test_offsets_file_reads_back_with_every_field(tmp_path):
    when = dt.datetime(2026, 11, 22, 3, 0, 0, tzinfo=dt.UTC)
    p = write_offsets(tmp_path / "offsets.yaml", SOLUTION, "irma4u", "RUN", when)
    doc = yaml.safe_load(p.read_text())
    assert doc == offsets_document(SOLUTION, "irma4u", "RUN", when)
    assert doc["lengths"] == [2.0, 2.01, 2.02, 2.03] and doc["yaw"] == 0.0031
    assert doc["pose"][2] == 1.0651 and doc["created"] == "2026-11-22T03:00:00Z"
    assert not (tmp_path / "offsets.yaml.tmp").exists()
    assert read_offsets(p) == doc
    bad = tmp_path / "bad.yaml"
    bad.write_text(p.read_text().replace("swivels:", "swivels_:"))
    with pytest.raises(ValueError, match=r"bad.yaml: field 'swivels' = None must be a list of n numbers"):
        read_offsets(bad)


def test_html_is_self_contained_with_svg_plots():
    t = np.arange(100) * 0.1
    tau = 100 + np.sin(t)[:, None] * np.arange(1, 5)
    page = render_html(summary(), t, tau, np.full_like(tau, 100.0))
    imgs = [base64.b64decode(i) for i in re.findall(r"data:image/svg\+xml;base64,([A-Za-z0-9+/=]+)", page)]
    assert len(imgs) == 2  # residuals and tensions
    assert all(i.startswith(b"<?xml") and b"<svg" in i and i.rstrip().endswith(b"</svg>") for i in imgs)
    assert "src='http" not in page and "<script" not in page
    assert "<td>1065.100</td><td>0.200</td>" in page


def test_report_renderer_child_writes_the_same_page_and_falls_back_when_gone(tmp_path):
    t = np.arange(200) * 0.1
    tau = 100 + np.sin(t)[:, None] * np.arange(1, 5)
    ref = np.full_like(tau, 100.0)
    write_html(tmp_path / "here.html", summary(), t, tau, ref)
    with ReportRenderer() as r:
        r.start()
        child = r.pid
        assert child is not None and r.alive()  # waiting, matplotlib loaded meanwhile
        assert r.write(tmp_path / "child.html", summary(), t, tau, ref) == tmp_path / "child.html"
        assert r.pid is None
        with pytest.raises(ChildProcessError):
            os.waitpid(child, os.WNOHANG)  # it wrote the page, ended and was reaped
    assert (tmp_path / "child.html").read_bytes() == (tmp_path / "here.html").read_bytes()
    # the child killed (or never started): the page is rendered in this process
    r = ReportRenderer().start()
    os.kill(r.pid, signal.SIGKILL)
    r.write(tmp_path / "fallback.html", summary(), t, tau, ref)
    assert (tmp_path / "fallback.html").read_bytes() == (tmp_path / "here.html").read_bytes()
    # a routine that stopped before its report: close() ends the waiting child
    r = ReportRenderer().start()
    child = r.pid
    r.close()
    assert r.pid is None
    with pytest.raises(ChildProcessError):
        os.waitpid(child, os.WNOHANG)


def _state(pid: int, want: str) -> str:
    """The process state letter of ``pid`` once it is one of ``want`` (signals land asynchronously), or the
    last one seen after 2 s."""
    import time

    end = time.monotonic() + 2.0
    while True:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
        if state in want or time.monotonic() > end:
            return state
        time.sleep(0.005)


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="reads process states from /proc")
def test_report_renderer_is_stopped_while_the_control_loop_runs(tmp_path):
    t = np.arange(50) * 0.1
    tau = np.full((50, 4), 100.0)
    with ReportRenderer() as r:
        r.start()
        with r.paused():
            assert _state(r.pid, "T") == "T"  # stopped: it takes no CPU from the loop
        assert _state(r.pid, "RSD") in "RSD"  # continued
        assert r.write(tmp_path / "report.html", summary(), t, tau, tau) == tmp_path / "report.html"
    assert (tmp_path / "report.html").read_text().startswith("<!DOCTYPE html>")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_routine_leaves_no_stopped_renderer_behind():
    # the routine killed outright (no finally runs) while its renderer is stopped for the control loop
    code = ("import sys, time; from acquisition.report import ReportRenderer; r = ReportRenderer().start(); "
            "p = r.paused(); p.__enter__(); print(r.pid, flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        renderer = int(proc.stdout.readline())
        assert _state(renderer, "T") == "T"
    finally:
        proc.kill()
    proc.wait()
    end = time.monotonic() + 5.0
    while time.monotonic() < end:
        try:
            with open(f"/proc/{renderer}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] in "ZX":
                    break  # killed, waiting for init to reap it
        except FileNotFoundError:
            break  # killed and reaped
        time.sleep(0.01)
    else:
        os.kill(renderer, signal.SIGKILL)
        pytest.fail("the stopped renderer outlived its routine")
    proc.stdout.close()


def test_progress_bar_draws_on_a_tty_only():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    s = Tty()
    bar = ProgressBar(200.0, stream=s, min_interval=0.0)
    bar.update(50.0, "hold", 2, 9)
    bar.close()
    assert "25.0%" in s.getvalue() and "setpoint 3/9" in s.getvalue() and "~  150 s left" in s.getvalue()
    plain = io.StringIO()
    quiet = ProgressBar(200.0, stream=plain, min_interval=0.0)
    quiet.update(50.0, "hold", 2, 9)
    quiet.close()
    assert plain.getvalue() == ""
