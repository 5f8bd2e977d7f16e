"""The damage policy (docs/run-format.md) on damaged input, property-based: the run reader and both IRMA
importers, on files truncated anywhere, with lines inserted, duplicated, reordered, fields cut or made
non-numeric. Never a traceback (a damaged file is read, with one warning, or refused with one sentence),
never a silently different result: a run read without a warning is the undamaged one, or (a file cut
exactly at a line end, which cannot be told from a shorter file) its first samples."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acquisition.damage import DamagedInputWarning
from acquisition.importers import PARTIAL, IrmaImportError, irma_run
from acquisition.logcycles import cycle_tolerance
from acquisition.runlog import RunFormatError, read_run
from acquisition.runwriter import new_run, write_run

SETTINGS = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# ---- damage, applied to the lines of a text file ----------------------------------------------------------

JUNK = st.text(alphabet="0123456789.,-+eEnaNIf x#\t", max_size=30)
damage_op = st.one_of(
    st.tuples(st.just("insert"), st.floats(0, 1), JUNK),
    st.tuples(st.just("duplicate"), st.floats(0, 1), st.floats(0, 1)),
    st.tuples(st.just("swap"), st.floats(0, 1), st.floats(0, 1)),
    st.tuples(st.just("cut_fields"), st.floats(0, 1), st.integers(1, 3)),
    st.tuples(st.just("non_numeric"), st.floats(0, 1), st.sampled_from(["abc", "", "1.2.3", "nan", "inf", "--"])),
)
damages = st.tuples(st.lists(damage_op, min_size=1, max_size=4), st.none() | st.floats(0, 1))


def _at(lines: list[str], x: float, first: int) -> int:
    return first + min(int(x * (len(lines) - first)), len(lines) - first - 1)


def damage_text(text: str, ops, cut: float | None, first: int = 0) -> tuple[bytes, bool]:
    """The damaged file, and whether it was cut exactly at a line end (a shorter file, not a damaged one).
    Lines before ``first`` (a header) are left alone by the line operations."""
    lines = text.splitlines()
    for kind, x, arg in ops:
        k = _at(lines, x, first)
        if kind == "insert":
            lines.insert(k, arg)
        elif kind == "duplicate":
            lines.insert(_at(lines, arg, first), lines[k])
        elif kind == "swap":
            j = _at(lines, arg, first)
            lines[k], lines[j] = lines[j], lines[k]
        elif kind == "cut_fields":
            cells = lines[k].split(",")
            lines[k] = ",".join(cells[: max(1, len(cells) - arg)])
        else:
            cells = lines[k].split(",")
            cells[min(len(cells) - 1, 2)] = arg
            lines[k] = ",".join(cells)
    data = ("\n".join(lines) + "\n").encode()
    if cut is None:
        return data, False
    n = int(cut * len(data))
    return data[:n], n > 0 and data[n - 1 : n] == b"\n"


def read_quietly(fn, *args):
    """(result or the error, the warnings): a result with its warnings, or an error of the policy's kind."""
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        try:
            out = fn(*args)
        except (RunFormatError, IrmaImportError) as exc:
            text = str(exc)
            assert text.endswith(".") and "\n" not in text and str(args[0]) in text, text
            return exc, rec
    damaged = [w for w in rec if issubclass(w.category, DamagedInputWarning)]
    assert len(damaged) <= 1 and len(damaged) == len([w for w in rec if issubclass(w.category, UserWarning)])
    if damaged:
        assert str(damaged[0].message).endswith(f"; {len(out)} samples kept.")
    return out, damaged


def assert_same_or_prefix(got, want, names, cut_at_line_end: bool):
    """A run read without a warning: the undamaged run or, cut at a line end, its first samples."""
    k = len(got)
    assert k == len(want) or (cut_at_line_end and k < len(want)), (k, len(want))
    for name in names:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name)[:k], err_msg=name)


# ---- the run reader -------------------------------------------------------------------------------------


def _run():
    rng = np.random.default_rng(7)
    N = 25
    return new_run("irma4u", "equilibrium", 0.1, "test", t=0.1 * np.arange(N), tau=rng.uniform(50, 150, (N, 4)),
                   tau_ref=rng.uniform(50, 150, (N, 4)), dl=rng.normal(0, 0.1, (N, 4)),
                   dsigma=rng.normal(0, 0.1, (N, 4)), roll=rng.normal(0, 0.05, N), pitch=rng.normal(0, 0.05, N),
                   dyaw=rng.normal(0, 0.05, N), phase=["hold"] * N, setpoint=np.arange(N) % 3)


@pytest.fixture(scope="module")
def good_run(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("good") / "run"
    write_run(folder, _run())
    return folder


RUN_COLUMNS = ("t", "tau", "tau_ref", "dl", "dsigma", "roll", "pitch", "dyaw", "setpoint")


@SETTINGS
@given(damage=damages)
def test_run_reader_on_damaged_samples(good_run, tmp_path_factory, damage):
    folder = tmp_path_factory.mktemp("bad")
    (folder / "run.yaml").write_bytes((good_run / "run.yaml").read_bytes())
    data, at_line_end = damage_text((good_run / "samples.csv").read_text(), *damage, first=1)
    (folder / "samples.csv").write_bytes(data)
    want = read_run(good_run)
    got, warned = read_quietly(read_run, folder)
    if isinstance(got, Exception):
        return
    assert np.all(np.diff(got.t) > 0)
    index = np.searchsorted(want.t, got.t)
    assert np.all(index < len(want)) and np.array_equal(want.t[np.minimum(index, len(want) - 1)], got.t)
    for name in RUN_COLUMNS:  # every sample kept is a sample of the run, unchanged
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name)[index], err_msg=name)
    if not warned:
        assert_same_or_prefix(got, want, RUN_COLUMNS, at_line_end)


# ---- the raw IRMA log -----------------------------------------------------------------------------------


def _targets(k: int) -> float:
    """Target tension of experiment cycle k (N): pretension, a hold at 120 N, a ramp, a hold at 140 N."""
    return 100.0 if k < 3 else 120.0 if k < 16 else 120.0 + 5 * (k - 15) if k < 19 else 140.0


def _log_text(t0: float = 0.0, early: float = 0.0) -> str:
    """A raw log: 5 homing cycles from ``t0`` s, a 4.5 s pause, 34 experiment cycles; cable 0's line of each
    cycle stamped ``early`` s before the others (as the controller does); stamps printed as it prints them
    (6 significant digits)."""
    lines = []
    times = [t0 + 0.1 * k for k in range(5)] + [t0 + 5.0 + 0.1 * k for k in range(34)]
    for j, t in enumerate(times):
        k = j - 5
        target = 100.0 if k < 0 else _targets(k)
        for i in range(4):
            length = 2.27 + 0.001 * j + 0.01 * i
            lines.append(f"3,{t - early * (i == 0):.6g},{i},10,{1000 * j + i},0,{5 + i},{length:.6f},0.0,"
                         f"{target + 0.1 * i:.3f},{target:.3f},0,4,{0.5 + 0.001 * j:.6f}")
        lines.append(f"5,{t:.6g},{0.1 * j:.3f},{-0.2 * j:.3f},{1.0 + 0.01 * j:.3f}")
        lines.append(f"6,{t:.6g},1,2,3")
    return "\n".join(lines) + "\n"


LOG_COLUMNS = ("t", "tau", "tau_ref", "dl", "dsigma", "roll", "pitch", "dyaw")


@SETTINGS
@given(damage=damages)
def test_raw_log_importer_on_damaged_lines(tmp_path_factory, damage):
    folder = tmp_path_factory.mktemp("log")
    good, bad = folder / "good.log", folder / "bad.log"
    good.write_text(_log_text())
    data, at_line_end = damage_text(good.read_text(), *damage)
    bad.write_bytes(data)
    want = irma_run(good)
    got, warned = read_quietly(irma_run, bad)
    if isinstance(got, Exception):
        return
    assert np.all(np.diff(got.t) > 0)
    if not warned:
        assert got.meta["time_origin"] == want.meta["time_origin"]
        assert_same_or_prefix(got, want, LOG_COLUMNS, at_line_end)


def test_the_synthetic_log_imports_cleanly(tmp_path):
    f = tmp_path / "good.log"
    f.write_text(_log_text())
    run, warned = read_quietly(irma_run, f)
    assert not warned and len(run) == 34 and len(run.setpoints) == 2


# ---- a cycle's lines stamped apart (issue 28i) ------------------------------------------------------------

SKEWED = 95.00054  # cable 0 0.1 ms early: printed 0.1 ms apart below 100 s, 1 ms apart past it ("100" / "100.001")


def _skewed_log(tmp_path: Path, drop=(), move=None, add=()) -> Path:
    """The skewed log with the lines holding the strings of ``drop`` removed, the line starting with
    ``move[0]`` restamped ``move[1]``, the lines of ``add`` appended."""
    lines = [line for line in _log_text(SKEWED, 1e-4).splitlines() if not any(d in line for d in drop)]
    if move:
        lines = [line.replace(move[0], move[1], 1) if line.startswith(move[0]) else line for line in lines]
    f = tmp_path / "skewed.log"
    f.write_text("\n".join([*lines, *add]) + "\n")
    return f


def test_a_cycles_lines_stamped_a_tenth_of_a_ms_apart_are_one_cycle(tmp_path):
    """Failed before: every cycle was split in two partial ones and the log held no complete cycle."""
    text = _log_text(SKEWED, 1e-4)
    assert "3,95.0004,0," in text and "5,95.0005," in text and "3,100,0," in text and "5,100.001," in text
    even = tmp_path / "even.log"
    even.write_text(_log_text(SKEWED))  # the same log, every line of a cycle stamped alike
    run, warned = read_quietly(irma_run, _skewed_log(tmp_path))
    want = irma_run(even)
    assert not warned and len(run) == 34 and run.meta["homing"]["recording"]["samples"] == 5
    assert run.meta["time_origin"] == 100.001  # a cycle's time: its AHRS line's stamp
    for name in LOG_COLUMNS:
        np.testing.assert_array_equal(getattr(run, name), getattr(want, name), err_msg=name)
    np.testing.assert_allclose(cycle_tolerance(np.array([60.0, 200.0, 2000.0])), [1.1e-3, 2e-3, 11e-3])


def test_a_cycle_really_lacking_a_line_is_still_dropped_and_counted(tmp_path):
    f = _skewed_log(tmp_path, drop=["3,101.001,2,"])  # cable 2 of the cycle at 101.001 s is missing
    run, warned = read_quietly(irma_run, f)
    assert len(run) == 33 and 1.0 not in np.round(run.t, 6)  # the cycle is gone, no neighbour's line borrowed
    said = f"{f}: damaged input: 1 {PARTIAL} (first: the cycle at line 91); 33 samples kept."
    assert str(warned[0].message) == said
    f = _skewed_log(tmp_path, move=("3,102,0,", "3,102.051,0,"))  # half a period late: a cycle of its own
    run, warned = read_quietly(irma_run, f)
    assert len(run) == 33 and f"2 {PARTIAL}" in str(warned[0].message)


def test_a_cable_twice_in_a_skewed_cycle_is_a_conflict_or_a_repeat(tmp_path):
    line = next(x for x in _log_text(SKEWED, 1e-4).splitlines() if x.startswith("3,101,0,"))
    other = line.replace("3,101,0,", "3,101.001,0,").replace(",15000,", ",15001,")  # the AHRS line's stamp
    run, warned = read_quietly(irma_run, _skewed_log(tmp_path, add=[other]))
    assert len(run) == 33 and "1 same time as another line with other values" in str(warned[0].message)
    same = line.replace("3,101,0,", "3,101.001,0,")
    run, warned = read_quietly(irma_run, _skewed_log(tmp_path, add=[same]))
    assert len(run) == 34 and "1 repeated" in str(warned[0].message)


# ---- the authors' parsed .mat ---------------------------------------------------------------------------

FIELDS = ("t", "epsilon", "cable_length", "swivel", "tensions", "target_tensions")


def _parsed() -> dict[str, np.ndarray]:
    N = 34
    k = np.arange(N)
    target = np.array([_targets(j) for j in k])
    return {"t": 5.0 + 0.1 * k, "epsilon": np.vstack([0.01 * k, -0.02 * k, 0.001 * k]),
            "cable_length": 2.27 + 0.001 * k + 0.01 * np.arange(4)[:, None],
            "swivel": 0.5 + 0.001 * np.ones((4, N)) * k,
            "tensions": target + 0.1 * np.arange(4)[:, None], "target_tensions": np.tile(target, (4, 1))}


parsed_op = st.one_of(
    st.tuples(st.just("cut_field"), st.sampled_from(FIELDS), st.integers(1, 10)),
    st.tuples(st.just("non_finite"), st.sampled_from(FIELDS), st.floats(0, 1)),
    st.tuples(st.just("duplicate"), st.floats(0, 1), st.floats(0, 1)),
    st.tuples(st.just("swap"), st.floats(0, 1), st.floats(0, 1)),
    st.tuples(st.just("text_field"), st.sampled_from(FIELDS), st.just(0)),
)


def damage_parsed(st_: dict[str, np.ndarray], ops) -> dict:
    out = {name: np.atleast_2d(a).copy() for name, a in st_.items()}
    for kind, a, b in sorted(ops, key=lambda op: op[0] == "text_field"):  # a text field last: it has no samples
        N = min(v.shape[1] for v in out.values())
        if kind == "cut_field":
            out[a] = out[a][:, : max(0, out[a].shape[1] - b)]
        elif kind == "non_finite":
            out[a][0, min(int(b * N), N - 1)] = np.nan
        elif kind in ("duplicate", "swap"):
            i, j = min(int(a * N), N - 1), min(int(b * N), N - 1)
            for name, v in out.items():
                v = v[:, :N]
                if kind == "duplicate":
                    out[name] = np.insert(v, j, v[:, i], axis=1)
                else:
                    v[:, [i, j]] = v[:, [j, i]]
                    out[name] = v
        else:
            out[a] = np.array(["damaged"])
            break
    return out


@SETTINGS
@given(ops=st.lists(parsed_op, min_size=1, max_size=3), cut=st.none() | st.floats(0, 1))
def test_parsed_mat_importer_on_damaged_samples(tmp_path_factory, ops, cut):
    folder = tmp_path_factory.mktemp("mat")
    good, bad = folder / "good_parsed.mat", folder / "bad_parsed.mat"
    scipy.io.savemat(good, {"st": _parsed()})
    damaged = damage_parsed(_parsed(), ops)
    scipy.io.savemat(bad, {"st": damaged})
    if cut is not None:  # a file cut anywhere, past its MATLAB header
        data = bad.read_bytes()
        bad.write_bytes(data[: 128 + int(cut * (len(data) - 128))])
    want = irma_run(good)
    got, warned = read_quietly(irma_run, bad)
    if isinstance(got, Exception):
        return
    t_want = want.t + want.meta["time_origin"]
    t_got = got.t + got.meta["time_origin"]
    index = np.searchsorted(t_want, t_got)
    assert np.all(np.diff(t_got) > 0) and np.all(index < len(want))
    for name in LOG_COLUMNS[1:]:  # every sample kept is a sample of the recording, unchanged
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name)[index], err_msg=name)
    if not warned:  # nothing said, nothing lost: every field of the file was whole and of one length
        # (cutting one field, then a no-op swap that trims all to the shortest, writes a whole shorter recording)
        lengths = {v.shape[1] for v in damaged.values() if v.dtype.kind in "fiu"}
        assert len(lengths) == 1 and len(got) == lengths.pop()


def test_samples_cut_inside_the_header_are_refused(good_run, tmp_path):
    """A file that ends inside its header line (found by hypothesis: cut at 1.5 %, the last column read
    'setpo') was read as a run of 0 samples without a word; the header describes every line, so it is fatal."""
    (tmp_path / "run.yaml").write_bytes((good_run / "run.yaml").read_bytes())
    header = (good_run / "samples.csv").read_text().splitlines()[0]
    (tmp_path / "samples.csv").write_text(header[:-3])
    with pytest.raises(RunFormatError, match="header line is cut short"):
        read_run(tmp_path)
