"""A 4-channel load-cell amplifier emulated on a pty master (protocol: docs/protocols/loadcell.md).

Clocked by the simulator: :meth:`LoadCellEmulator.emit` is called once per control tick with the true
cable tensions and writes one line, the device sequence number growing by one per tick (also while the
line is disconnected, so that the host sees the gap). A reader thread answers ``$INFO``.

Sensor model per channel i (N): reading = gain_i * tau_i + offset_i + a_i + noise, where offset_i and
gain_i are the hidden effects of the simulation configuration, a_i a constant error drawn once within the
accuracy class (0.02 % of the 100 kg full scale) and the noise white Gaussian; the result is rounded to
0.01 N and flagged OVER beyond 110 % of full scale. Faults: :meth:`stick` (a channel repeats its last
value), :meth:`disconnect` (one channel reads OPEN, or the whole amplifier goes silent), :meth:`corrupt`.
Channels are 0-based in this API and 1-based in sentences for the operator.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivers import loadcell
from sim_backend.physics import play
from sim_backend.pty import GaussianBlocks, PtyEmulator, free_run, read_master

FULL_SCALE = 100.0 * 9.81  # N, the prototype's 100 kg cells


# N: the load change that moves a cell onto its other hysteresis branch (the rows' APPROACH_TENSION)
HYSTERESIS_LOAD = 2.0


class LoadCellEmulator(PtyEmulator):
    """One emulated amplifier on ``master_fd``; start the command thread with :meth:`start`."""

    thread_name = "loadcell-emulator"

    def __init__(
        self,
        master_fd: int,
        rng: np.random.Generator,
        channels: int = 4,
        offsets: Sequence[float] | None = None,
        gains: Sequence[float] | None = None,
        noise_std: float = 0.1,
        full_scale: float = FULL_SCALE,
        accuracy: float = 0.0002,
        rate_hz: float = 100.0,
        model: str | None = None,
        hysteresis: float = 0.0,
    ) -> None:
        super().__init__(master_fd, rng)
        self.n = channels
        offsets = np.zeros(channels) if offsets is None else np.asarray(offsets, dtype=float)
        gains = np.ones(channels) if gains is None else np.asarray(gains, dtype=float)
        if offsets.shape != (channels,) or gains.shape != (channels,):
            raise ValueError(f"load-cell offsets and gains need {channels} values each")
        self.noise_std = noise_std
        self.full_scale = full_scale
        self.rate_hz = rate_hz
        self.model = model or f"LC{channels}-SIM"
        accuracy_error = rng.uniform(-accuracy * full_scale, accuracy * full_scale, channels)
        # per channel (gain, offset N, accuracy error N) as plain floats: read at every tick
        self._errors = list(zip(gains.tolist(), offsets.tolist(), accuracy_error.tolist(), strict=True))
        self.seq = -1
        self._last = [0.0] * channels
        self._stuck = [False] * channels  # plain lists: read at every tick, numpy costs more than it saves
        self._open = [False] * channels
        self._decoder = loadcell.LineDecoder()
        self._normals = GaussianBlocks(rng, channels)  # the per-sample noise, drawn after the accuracy errors
        # hysteresis h, N (the loadcell_hysteresis hidden effect): the reading is h y lower, y = +1 on a rising
        # load, -1 on a falling one, reversed once the load left its extreme by HYSTERESIS_LOAD N
        self.hysteresis = float(hysteresis)
        self._y = [1.0] * channels  # the cells were loaded from zero
        self._ext = [0.0] * channels

    @property
    def gains(self) -> np.ndarray:
        """(n,) channel gains (fixed at construction)."""
        return np.array([g for g, _, _ in self._errors])

    @property
    def offsets(self) -> np.ndarray:
        """(n,) channel offsets, N (fixed at construction)."""
        return np.array([o for _, o, _ in self._errors])

    # ---- faults ----
    def stick(self, channel: int) -> None:
        """Channel ``channel`` (0-based) keeps repeating its last value."""
        self._stuck[channel] = True

    def unstick(self, channel: int) -> None:
        self._stuck[channel] = False

    def disconnect(self, channel: int | None = None) -> None:
        """One channel's bridge opens (reads OPEN), or with ``None`` the whole amplifier goes silent."""
        if channel is None:
            self._silent = True
        else:
            self._open[channel] = True

    def reconnect(self, channel: int | None = None) -> None:
        if channel is None:
            self._silent = False
        else:
            self._open[channel] = False

    # ---- the simulator's clock ----
    def measure(self, true_tensions: np.ndarray) -> np.ndarray:
        """Readings (n,) in N for the true tensions: gain, offset, accuracy error, noise, 0.01 N steps."""
        return np.array(self._measure(true_tensions))

    def _measure(self, true_tensions) -> list[float]:
        """:meth:`measure` as plain floats (numpy costs more than it saves on 4 channels); the same arithmetic,
        in the same order, and numpy's rounding (half to even of value * 100)."""
        tau = np.asarray(true_tensions, dtype=float).reshape(self.n).tolist()
        if self.hysteresis:
            tau = self._hysteresis(tau)
        std = self.noise_std
        # the noise is rng.normal(0.0, std, n), i.e. loc + scale * z for standard normal draws z
        value = [round((g * t + o + a + (0.0 + std * z)) * 100.0) / 100.0
                 for (g, o, a), t, z in zip(self._errors, tau, self._normals.take(), strict=True)]
        if any(self._stuck):
            value = [last if stuck else v for v, last, stuck in zip(value, self._last, self._stuck,
                                                                     strict=True)]
        self._last = value
        return value

    def _hysteresis(self, tau: list[float]) -> list[float]:
        """The true tensions as the bridge sees them: h lower on the rising branch, h higher on the falling."""
        for i, t in enumerate(tau):
            self._y[i], self._ext[i] = play(t, self._y[i], self._ext[i], HYSTERESIS_LOAD)
        return [t - self.hysteresis * y for t, y in zip(tau, self._y, strict=True)]

    def emit(self, sim_time: float, true_tensions: np.ndarray) -> int | None:
        """One control tick: write one line; returns its sequence number (None while silent)."""
        line = self.prepare(sim_time, true_tensions)
        if line is None:
            return None
        self.send(line)
        return self.seq

    def prepare(self, sim_time: float, true_tensions: np.ndarray) -> bytes | None:
        """The line of one control tick, measured and encoded (its sequence number counted, the noise drawn),
        for :meth:`send` to write when it is due; None while silent. ``emit`` is prepare, then send."""
        value = self._measure(true_tensions)
        with self._lock:
            self.seq += 1
            if self._silent:
                return None
            over = 1.1 * self.full_scale
            fields: list[float | str] = [loadcell.OPEN if is_open else loadcell.OVER if abs(v) > over else v
                                         for v, is_open in zip(value, self._open, strict=True)]
            return self._maybe_corrupt(loadcell.encode_sample(self.seq, fields))

    def send(self, line: bytes) -> None:
        """Write a line made by :meth:`prepare`."""
        with self._lock:
            self._write(line)

    def info_line(self) -> bytes:
        return loadcell.frame(f"INFO,{self.model},{self.n},{self.full_scale:.3f},{self.rate_hz:g}")

    def _serve(self) -> None:
        dec = _CommandSplitter()
        while not self._stop.is_set():
            data = read_master(self.fd, 0.02)
            for cmd in dec.feed(data):
                if cmd == "INFO" and not self._silent:
                    with self._lock:
                        self._write(self.info_line())


class _CommandSplitter:
    """Host commands ``$BODY*HH`` terminated by CR or LF; bodies with a good checksum come out."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        self.buf += data
        out = []
        while True:
            cut = min((i for i in (self.buf.find(b"\n"), self.buf.find(b"\r")) if i >= 0), default=-1)
            if cut < 0:
                break
            line = bytes(self.buf[:cut])
            del self.buf[: cut + 1]
            start = line.rfind(b"$")
            body = loadcell.unframe(line[start:]) if start >= 0 else None
            if body is not None:
                out.append(body)
        if len(self.buf) > loadcell.MAX_LINE:
            self.buf.clear()
        return out


def main(argv: list[str] | None = None) -> int:
    """Free-running demo for operators: ``python -m sim_backend.loadcell_emulator [tau_1 .. tau_4]`` (N).

    Creates a pty, prints its path (for ``cdpr devices read loadcells --port PATH``) and clocks the
    emulator on wall time at 100 Hz until interrupted; the simulator itself never free-runs.
    """
    import sys

    from sim_backend.pty import open_pty_pair

    tau = np.array([float(a) for a in (sys.argv[1:] if argv is None else argv)] or [50.0, 30.0, 55.0, 80.0])
    master, path = open_pty_pair()
    print(path, flush=True)
    emu = LoadCellEmulator(master, np.random.default_rng(0), channels=len(tau)).start()
    return free_run(emu, lambda t: emu.emit(t, tau), emu.rate_hz)


if __name__ == "__main__":
    raise SystemExit(main())
