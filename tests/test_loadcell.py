"""Load-cell line protocol (docs/protocols/loadcell.md): hand-written lines, property tests on random and
corrupted bytes, and the emulator's sensor model (offset, gain, accuracy, noise, faults) without a port."""

from __future__ import annotations

import functools
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import loadcell
from drivers.loadcell import InfoLine, LineDecoder, SampleLine, parse_line
from sim_backend.loadcell_emulator import FULL_SCALE, LoadCellEmulator
from sim_backend.pty import open_pty_pair

BODY = b"LC,7,52.10,30.95,55.87,81.20"
LINE = b"$LC,7,52.10,30.95,55.87,81.20*19\r\n"  # the example of docs/protocols/loadcell.md


def test_hand_written_line():
    assert functools.reduce(lambda a, b: a ^ b, BODY) == 0x19
    assert loadcell.encode_sample(7, [52.10, 30.95, 55.87, 81.20]) == LINE
    s = parse_line(LINE)
    assert isinstance(s, SampleLine) and s.seq == 7
    np.testing.assert_array_equal(s.tau, [52.10, 30.95, 55.87, 81.20])
    assert s.flags == ("", "", "", "")


def test_flags_info_and_command():
    body = b"LC,4294967295,OPEN,-0.25,OVER,0.00"
    cs = functools.reduce(lambda a, b: a ^ b, body)
    s = parse_line(b"$" + body + b"*" + f"{cs:02X}".encode() + b"\r\n")
    assert s.seq == 2**32 - 1 and s.flags == ("OPEN", "", "OVER", "")
    assert math.isnan(s.tau[0]) and s.tau[1] == -0.25 and math.isnan(s.tau[2])
    assert loadcell.frame("INFO") == b"$INFO*0E\r\n"  # 0x49 ^ 0x4E ^ 0x46 ^ 0x4F
    info = parse_line(loadcell.frame("INFO,LC4-SIM,4,981.000,100"))
    assert info == InfoLine("LC4-SIM", 4, 981.0, 100.0)


@pytest.mark.parametrize("bad", [
    b"$LC,7,52.10,30.95,55.87,81.20*18\r\n",  # checksum off by one
    b"$LC,7,52.10,30.95,55.87,81.20*1\r\n",  # one hex digit
    b"LC,7,52.10,30.95,55.87,81.20*19\r\n",  # no '$'
    b"$LC,7,52.10,30.95,55.87,81.2O*19\r\n",  # a letter O for a zero (and the checksum no longer fits)
    b"$LC,7*14\r\n",  # a good checksum but no channel
])
def test_bad_lines(bad):
    assert parse_line(bad) is None


def test_numbers_must_be_plain_decimals():
    for field in ("nan", "inf", "1e3", "1_0", "+5", " 5", "0x10"):
        assert parse_line(loadcell.frame(f"LC,1,{field},1.00")) is None, field
    assert parse_line(loadcell.frame("LC,-1,1.00")) is None
    assert parse_line(loadcell.frame("LC,4294967296,1.00")) is None  # past the 32-bit counter


def test_garbage_before_a_line_is_skipped_and_counted():
    dec = LineDecoder()
    out = dec.feed(b"\x00\xff$LC,3,1.0" + LINE + b"junk\r\n")
    assert [m.seq for m in out] == [7]
    assert dec.bad_lines == 1  # the "junk" line
    assert dec.bytes_discarded == len(b"\x00\xff$LC,3,1.0") + len(b"junk\r\n")
    assert dec.resyncs == 1


values = st.lists(st.one_of(st.floats(-1000, 1000, allow_nan=False).map(lambda v: round(v, 2)),
                            st.sampled_from(["OPEN", "OVER"])), min_size=1, max_size=8)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), values)
def test_round_trip(seq, vals):
    s = parse_line(loadcell.encode_sample(seq, vals))
    assert s.seq == seq
    for v, t, f in zip(vals, s.tau, s.flags, strict=True):
        if isinstance(v, str):
            assert f == v and math.isnan(t)
        else:
            assert f == "" and t == pytest.approx(v, abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=1500), st.lists(st.integers(1, 64), max_size=20))
def test_random_bytes_never_raise(data, cuts):
    dec, i = LineDecoder(), 0
    for c in cuts:
        dec.feed(data[i:i + c])
        i += c
    dec.feed(data[i:])
    parse_line(data)
    assert len(dec._buf) <= loadcell.MAX_LINE


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), st.integers(0, 10**6), values, st.lists(st.integers(1, 40), max_size=10))
def test_back_in_sync_by_the_next_line(garbage, seq, vals, cuts):
    a, b = loadcell.encode_sample(seq, vals), loadcell.encode_sample(seq + 1, vals)
    dec, data, out, i = LineDecoder(), garbage + a + b, [], 0
    for c in cuts:
        out += dec.feed(data[i:i + c])
        i += c
    out += dec.feed(data[i:])
    # the first good line is lost only when garbage without a line feed ran on for more than 256 bytes
    # into it (the overlong-line guard), or when garbage made of a valid '$...*HH' body precedes it
    seqs = [m.seq for m in out if isinstance(m, SampleLine)]
    assert seqs[-1] == seq + 1
    tail = garbage[garbage.rfind(b"\n") + 1:]
    if len(tail) + len(a) <= loadcell.MAX_LINE and b"$" not in tail:
        assert seqs[-2:] == [seq, seq + 1]


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 10**6), min_size=2, max_size=10), st.data())
def test_corrupted_lines_are_dropped_not_misread(seqs, data):
    lines = [loadcell.encode_sample(s, [1.0, 2.0]) for s in seqs]
    hit = data.draw(st.integers(0, len(lines) - 1))
    b = bytearray(lines[hit])
    pos = data.draw(st.integers(0, len(b) - 3))  # anywhere in '$...*HH', keeping the CR LF
    b[pos] ^= data.draw(st.integers(1, 255))
    lines[hit] = bytes(b)
    got = [m.seq for m in LineDecoder().feed(b"".join(lines)) if isinstance(m, SampleLine)]
    # one flipped byte always breaks the XOR checksum or the framing: that line is dropped, no other
    assert got == [s for k, s in enumerate(seqs) if k != hit]


# ---- the emulator's sensor model (no port needed: it writes to a pty nobody reads) ----


@pytest.fixture()
def master():
    fd, _ = open_pty_pair()
    yield fd
    os.close(fd)


def test_emulator_model_offset_gain_accuracy_noise(master):
    emu = LoadCellEmulator(master, np.random.default_rng(3), offsets=[5.0, -3.0, 0.0, 1.5],
                           gains=[1.02, 1.0, 0.97, 1.0], noise_std=0.1)
    true = np.array([50.0, 30.0, 55.0, 80.0])
    m = np.array([emu.measure(true) for _ in range(4000)])
    expected = np.array([1.02 * 50 + 5, 30 - 3, 0.97 * 55, 81.5])
    acc = 0.0002 * FULL_SCALE
    assert np.all(np.abs(m.mean(0) - expected) <= acc + 0.01)  # the accuracy-class error, plus sampling
    assert np.all(np.abs(m.std(0) - 0.1) < 0.01)
    assert np.allclose(np.round(m * 100), m * 100, rtol=0, atol=1e-6)  # 0.01 N steps
    assert np.ptp(m.mean(0) - expected) > 0  # the per-channel accuracy errors differ


def test_emulator_same_seed_same_bytes_and_faults(master):
    lines = []
    for _ in range(2):
        emu = LoadCellEmulator(master, np.random.default_rng(11), noise_std=0.2)
        lines.append([loadcell.encode_sample(k, emu.measure(np.full(4, 40.0))) for k in range(20)])
    assert lines[0] == lines[1]
    emu = LoadCellEmulator(master, np.random.default_rng(11))
    first = emu.measure(np.full(4, 40.0))
    emu.stick(2)
    later = [emu.measure(np.full(4, 60.0)) for _ in range(5)]
    assert all(r[2] == first[2] for r in later) and all(abs(r[0] - 60) < 1 for r in later)
    assert emu.emit(0.0, np.full(4, 10.0)) == 0
    emu.disconnect(1)
    assert emu.emit(0.01, np.full(4, 10.0)) == 1
    emu.disconnect()
    assert emu.emit(0.02, np.full(4, 10.0)) is None
    emu.reconnect()
    assert emu.emit(0.03, np.full(4, 10.0)) == 3  # the counter kept going while silent
