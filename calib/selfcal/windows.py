"""Equilibrium windows found from the signals, judged against the run's own noise and matched to the plan.

Stillness (:class:`Stillness`). Over a short centred span, every cable length, swivel angle, roll and pitch
stays within a range and the tension ripple (standard deviation over the span) stays within a tolerance.
Each channel's range is the larger of a fixed floor (the prototype's: 2 mm, 0.1 deg, 0.3 deg) and what the
run itself shows when nothing moves: ``noise_factor`` times the channel's sample noise (robust scale of its
second differences, which a slow motion leaves near zero) plus ``drift_factor`` times its slow drift (the
median change of the span mean from one span to the next over the samples the noise alone calls still: a
sway inside the windows; a run that never rests has no drift to call its motion).
The ripple tolerance is the paper's: the load cells' uncertainty or, if larger, ``ripple_factor`` times the
noise floor of the tensions. Runs of still samples lasting at least ``min_duration_s`` are windows.
The online detector of ``cdpr startup`` (acquisition.equilibrium) applies the same object: thresholds by
:meth:`Stillness.of_samples` on the samples it has seen, :meth:`Stillness.judge` on its latest span.

Windows and the plan (:func:`search_windows`). Consecutive windows at the same equilibrium (mean tensions
and lengths the same within the tolerances, nothing else visited in between) are one window. With planned
setpoints (run.yaml ``procedure.setpoints`` or an imported run's reference steps) each setpoint gets at most
one window, in plan order (an order-keeping alignment on the relative distance of the window's mean tension
or reference to the setpoint); a setpoint left without one gets the stillest stretch near its tensions as a
``quasi`` window, or is named with its reason. Still stretches matching no setpoint (the rest before the
sequence, the return to the pretension, a pause) are listed and not used unless ``use_unmatched``.
Without a plan the pretension rest is dropped and an unusually long gap between windows gets its stillest
stretch as a quasi window (the platform passed an equilibrium swinging slowly: the acceleration it leaves in
the statics is small next to the tension noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.chi2 import chi2_isf
from calib.robot import Robot
from calib.robust import median
from calib.selfcal.settle import SettleTest, quiet_noise, sample_noise

CHANNELS = ("length", "swivel", "tilt")


@dataclass(frozen=True)
class WindowOptions:
    """Stillness floors (SI units), noise multiples, durations (s) and plan matching."""

    span_s: float = 0.5
    min_duration_s: float = 1.0
    length_tol: float = 0.002  # m, floor of the cable-length range over a span
    swivel_tol: float = math.radians(0.1)
    tilt_tol: float = math.radians(0.3)
    noise_factor: float = 6.0  # range over a span allowed per unit of sample noise
    drift_factor: float = 2.0  # and per unit of slow drift over a span
    ripple_factor: float = 3.0
    setpoint_tol: float = 0.15  # relative distance |mean tau - setpoint| / |setpoint| to call it a match
    pretension_band: float = 5.0  # N: tau_ref departing this much from its first value ends the pretension
    gap_factor: float = 2.0
    quasi_max: float = 10.0
    use_unmatched: bool = False  # with a plan, also use the still stretches that match no setpoint
    ends_s: float = 0.1  # s of samples at each end of a window compared with the rest of it
    # false-alarm probability of the ends test at rest (per end and step; 0: no test). Off by default: on the
    # real sc_8_final (parsed) it left 7 of the 8 equilibria and moved the raw log's estimate solve 6.6 -> 13 mm
    # from zeta_0_real; 1e-3 is what issue 29 measured on the simulator (docs/windows.md)
    ends_p: float = 0.0
    ends_margin_s: float = 0.2  # s cut beyond an end the test found moving
    # s: the farthest distance between an end and the centre of the rest that a sway's slow wander grows over
    # (the online detector's longer blocks take half of settle_s)
    ends_reach_s: float = 0.5
    # the online detector (acquisition.equilibrium) calls a rest only after settle_s of still samples that the
    # ends test at settle_p (when ends_p is 0) finds resting end to end: a hold-time rule for new startups
    settle_s: float = 3.0
    settle_p: float = 1e-3
    # the settle test (calib.selfcal.settle): blocks of settle_block_s, false-alarm probability settle_test_p per
    # window at rest (0: off); one criterion, the same in the offline search and the online detector
    settle_block_s: float = 0.5
    settle_test_p: float = 0.05
    # s cut from the head of every window the settle test judged (0: none): the approach's last samples, where
    # the hold's tensions still converge by 1-2 N under the load cells' noise of a sample (docs/windows.md)
    settle_margin_s: float = 0.5
    # s cut from the tail of such a window (0: none): the next move's first samples, whose quintic leaves its hold
    # value with zero speed and acceleration and moves the tensions by less than their noise at first
    settle_tail_margin_s: float = 0.1
    # the tail too (off: on the real robot the next quintic's start; it moved the 27-pose run's estimate 4 mm)
    settle_tail: bool = False


@dataclass(frozen=True)
class Window:
    """Samples first..last (inclusive, 0-based) held in equilibrium; setpoint index or -1; quasi when the
    window is the stillest stretch rather than a still one."""

    first: int
    last: int
    setpoint: int = -1
    quasi: bool = False

    @property
    def slice(self) -> slice:
        return slice(self.first, self.last + 1)

    @property
    def size(self) -> int:
        return self.last - self.first + 1

    @property
    def middle(self) -> int:
        return (self.first + self.last) // 2


@dataclass(frozen=True)
class MissingSetpoint:
    """A planned setpoint without a window and why, one sentence."""

    setpoint: int
    reason: str


@dataclass(frozen=True)
class WindowSearch:
    """What :func:`search_windows` found: ``found`` every window (time order, labelled), ``used`` those that
    become poses, ``planned`` the number of planned setpoints (0: no plan), ``missing`` the planned setpoints
    without a window, ``thresholds`` the stillness ranges per channel (SI), ``ripple_tol`` (N) and ``ends`` the
    test that cut the windows' moving ends."""

    found: list[Window]
    used: list[Window]
    planned: int
    missing: list[MissingSetpoint]
    thresholds: dict[str, np.ndarray] = field(default_factory=dict)
    ripple_tol: float = 0.0
    ends: EndsTest | None = None  # the ends test the windows were cut with


def _centred(stat: np.ndarray, w: int, size: int) -> np.ndarray:
    """Pad a sliding statistic (size - w + 1, ...) to (size, ...) so that entry i describes the span around i."""
    lo = w // 2
    pad = [(lo, size - stat.shape[0] - lo)] + [(0, 0)] * (stat.ndim - 1)
    return np.pad(stat, pad, mode="edge")


def noise_floor(x: np.ndarray) -> np.ndarray:
    """Robust white-noise standard deviation per column of x (N, c) from first differences (MAD)."""
    d = np.diff(x, axis=0)
    mad = median(np.abs(d - median(d, axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(2.0)


def slow_drift(x: np.ndarray, w: int, rest: np.ndarray) -> np.ndarray:
    """Per column of x (N, c), the median change of the w-sample mean from one span to the next over the
    samples ``rest`` (N,) judged at rest: how much a platform at rest still wanders over a span (sway, drift);
    zero when fewer than a tenth of the samples rest."""
    N = x.shape[0]
    if N < 2 * w or rest.sum() < max(2 * w, N // 10):
        return np.zeros(x.shape[1:])
    c = np.cumsum(np.r_[np.zeros((1,) + x.shape[1:]), x], axis=0)
    m = (c[w:] - c[:-w]) / w  # mean of x[i : i + w]
    change = np.abs(m[w:] - m[:-w])  # entry i: around sample i + w
    keep = rest[w : w + change.shape[0]]
    return median(change[keep], axis=0) if keep.any() else np.zeros(x.shape[1:])


def running_max(x: np.ndarray, w: int) -> np.ndarray:
    """The maximum of every ``w`` consecutive rows of ``x`` (N, c): (N - w + 1, c), entry k that of
    x[k : k + w]; exact, O(N) (van Herk / Gil-Werman: prefix and suffix maxima within blocks of ``w``)."""
    n = x.shape[0]
    blocks = -(-n // w)
    pad = np.full((blocks * w - n, *x.shape[1:]), -np.inf)
    b = np.concatenate([x, pad]).reshape(blocks, w, -1)
    ahead = np.maximum.accumulate(b, axis=1).reshape(blocks * w, -1)
    behind = np.maximum.accumulate(b[:, ::-1], axis=1)[:, ::-1].reshape(blocks * w, -1)
    return np.maximum(behind[: n - w + 1], ahead[w - 1 : n]).reshape(n - w + 1, *x.shape[1:])


@dataclass(frozen=True)
class Activity:
    """What the signals do over each centred span of ``span`` samples: the range (max - min) per channel and
    column, and the largest standard deviation of the tensions (N); (N, ...) per sample."""

    span: int
    ranges: dict[str, np.ndarray]
    ripple: np.ndarray

    @classmethod
    def of(cls, tau: np.ndarray, channels: dict[str, np.ndarray], w: int) -> Activity:
        size = tau.shape[0]
        if size < w:
            return cls(w, {c: np.full(x.shape, np.inf) for c, x in channels.items()}, np.full(size, np.inf))
        m, lo = size - w + 1, w // 2
        # every channel's columns side by side: one running max and one running min (:func:`running_max`);
        # entry i covers x[i - w//2 : i - w//2 + w], the edges repeat the first and last full span
        names = list(channels)
        x = np.concatenate([channels[c].reshape(size, -1) for c in names], axis=1)
        rng = np.empty_like(x)
        rng[lo : lo + m] = running_max(x, w) + running_max(-x, w)
        rng[:lo] = rng[lo]
        rng[lo + m :] = rng[lo + m - 1]
        ranges, start = {}, 0
        for c in names:
            width = channels[c].reshape(size, -1).shape[1]
            ranges[c] = rng[:, start : start + width]
            start += width
        y = tau - tau.mean(axis=0)
        c1 = np.zeros((size + 1, y.shape[1]))
        c2 = np.zeros((size + 1, y.shape[1]))
        np.cumsum(y, axis=0, out=c1[1:])
        np.cumsum(y * y, axis=0, out=c2[1:])
        mean = (c1[w:] - c1[:-w]) / w
        var = np.clip((c2[w:] - c2[:-w]) / w - mean * mean, 0.0, None)
        return cls(w, ranges, _centred(np.sqrt(var.max(axis=1)), w, size))


MEDIAN_ABS = 0.6745  # median |x| / sigma of a Gaussian x


@dataclass(frozen=True)
class EndsTest:
    """Whether a still stretch rests all through: each end (its first and last ``q`` samples) against the rest
    of the stretch, every channel at once (the tensions, whose ripple is the paper's criterion, the lengths,
    swivels, roll and pitch: a platform that still moves moves them all). At rest the difference of the two
    means of a column has the variance ``sigma^2 (1/q + 1/r)`` of white noise of the sample sigma (r samples in
    the rest) plus ``slow``, the variance of the slow wander of a mean (a sway) at the distance of the two
    parts; the sum over the
    columns of the squared differences over those variances is then chi2 with one degree of freedom per
    column, and an end whose sum exceeds its ``1 - p`` quantile still moves (a wobble settling after a move,
    the start of the next one): it is cut, and ``margin`` samples more with it (the motion that the noise hid
    next to the one it showed).

    ``sigma`` and ``slow`` are per channel (``tension`` and the :func:`still_channels`), per column, SI:
    ``sigma`` the channel's sample noise (:func:`quiet_noise`), ``slow`` the variance per span of the
    difference of two consecutive span means beyond what the white noise gives, from their median change
    (:func:`slow_drift`) over the samples at rest."""

    span: int
    q: int
    margin: int
    limit: float
    sigma: dict[str, np.ndarray]
    slow: dict[str, np.ndarray]
    reach: float = 1.0  # spans: the farthest distance of an end from the rest's centre the slow wander grows over

    @classmethod
    def of_samples(cls, tau: np.ndarray, channels: dict[str, np.ndarray], span: int, rest: np.ndarray,
                   options: WindowOptions, act: Activity) -> EndsTest:
        """The test of a run (tensions (N, n) N, ``channels`` as :func:`still_channels`, ``rest`` (N,) the
        samples the ranges call still, ``act`` their :class:`Activity`), ends ``options.ends_s`` and margin
        ``options.ends_margin_s`` long for a span of ``span`` samples of ``options.span_s``. The slow wander
        is measured where the spans also move within ``noise_factor`` quiet sigmas alone, not the floors: a
        platform still swinging by a millimetre passes those, and would pass for a sway."""
        every = {"tension": tau} | dict(channels)
        floors = {"length": options.length_tol, "swivel": options.swivel_tol, "tilt": options.tilt_tol}
        # a sigma at least a twelfth of the channel's range floor: a reading that sits on its counts does not
        # make a few counts of quasi-static motion at a window's end a move
        sigma = {c: np.maximum(quiet_noise(x), floors.get(c, 0.0) / 12.0) for c, x in every.items()}
        strict = rest.copy()
        for c, r in act.ranges.items():
            strict &= np.all(r <= options.noise_factor * sigma[c], axis=1)
        slow = {c: np.clip((slow_drift(x, span, strict) / MEDIAN_ABS) ** 2 / 2.0 - sigma[c] ** 2 / span, 0.0, None)
                for c, x in every.items()}
        per = options.span_s / span  # s per sample
        q = max(1, int(round(options.ends_s / per)))
        columns = sum(int(np.prod(x.shape[1:])) for x in every.values())
        reach = max(1.0, options.ends_reach_s / options.span_s)
        return cls(span, q, int(round(options.ends_margin_s / per)), chi2_isf(options.ends_p, columns),
                   sigma, slow, reach)

    def scores(self, block: dict[str, np.ndarray]) -> tuple[float, float]:
        """The chi2 of the start and of the end of a block (channels (L, c) as ``sigma``) against the rest of
        it, over the limit (<= 1: at rest); (inf, inf) when it holds fewer than 2 q samples."""
        L = next(iter(block.values())).shape[0]
        q, r = self.q, L - self.q
        if r < self.q:
            return math.inf, math.inf
        # spans between the centres of an end and of the rest: a sway's mean wanders further the further apart
        dist = min(0.5 * L / self.span, self.reach)
        head = tail = 0.0
        for c, x in block.items():
            x = x.reshape(L, -1)
            var = np.maximum(self.sigma[c] ** 2 * (1.0 / q + 1.0 / r) + self.slow[c] * dist**2, 1e-300)
            total = x.sum(axis=0)
            first, last = x[:q].sum(axis=0), x[-q:].sum(axis=0)
            head += float(np.sum((first / q - (total - first) / r) ** 2 / var))
            tail += float(np.sum((last / q - (total - last) / r) ** 2 / var))
        return head / self.limit, tail / self.limit

    def trim(self, tau: np.ndarray, channels: dict[str, np.ndarray], min_len: int = 2) -> tuple[int, int]:
        """Samples (a, b) to cut from the start and the end of a still stretch (tensions (L, n), channels
        (L, c)): one at a time from the end further off, until both ends rest, then ``margin`` more at each end
        that was cut; the whole stretch (a + b = L) when fewer than ``min_len`` samples would be left."""
        every = {"tension": tau} | dict(channels)
        L = tau.shape[0]
        a, b = 0, 0
        while L - a - b >= max(min_len, 2 * self.q):
            head, tail = self.scores({c: x[a : L - b] for c, x in every.items()})
            if max(head, tail) <= 1.0:
                a += self.margin if a else 0
                b += self.margin if b else 0
                return (a, b) if L - a - b >= min_len else (a, L - a)
            if head >= tail:
                a += 1
            else:
                b += 1
        return a, L - a


@dataclass(frozen=True)
class Stillness:
    """The stillness test of one run: span (samples), range per channel (SI, per column) and ripple tolerance
    (N). ``parts`` gives per sample the largest ratio of a channel's range over the span to its limit and the
    ripple over its tolerance; still where both are <= 1."""

    span: int
    thresholds: dict[str, np.ndarray]
    ripple_tol: float
    ends: EndsTest | None = None
    settle: SettleTest | None = None

    @classmethod
    def of_samples(
        cls, tau: np.ndarray, channels: dict[str, np.ndarray], span: int, options: WindowOptions,
        ripple_floor: float, act: Activity | None = None,
    ) -> Stillness:
        """Thresholds from the samples' own noise (tensions (N, n) N, ``channels`` as :func:`still_channels`),
        then their drift over the samples that noise alone calls still, floored at the options' tolerances:
        per channel max(floor, noise_factor x sample noise + drift_factor x drift); ripple tolerance
        max(ripple_floor, ripple_factor x the tensions' noise floor) (N). ``act``: their Activity if known."""
        w = span
        act = act if act is not None else Activity.of(tau, channels, w)
        floors = {"length": options.length_tol, "swivel": options.swivel_tol, "tilt": options.tilt_tol}
        tau_noise = float(noise_floor(tau).max()) if tau.shape[0] > 1 else 0.0
        ripple_tol = max(ripple_floor, options.ripple_factor * tau_noise)
        spread = {c: options.noise_factor * sample_noise(x) for c, x in channels.items()}
        noise = {c: np.maximum(floors[c], s) for c, s in spread.items()}
        kin, ripple = cls(w, noise, ripple_tol).parts(act)
        rest = (kin <= 1.0) & (ripple <= 1.0)
        thr = {c: np.maximum(noise[c], spread[c] + options.drift_factor * slow_drift(x, w, rest))
               for c, x in channels.items()}
        ends = EndsTest.of_samples(tau, channels, w, rest, options, act) if options.ends_p > 0 else None
        settle = settle_test(tau, channels, w, options) if options.settle_test_p > 0 else None
        return cls(w, thr, ripple_tol, ends, settle)  # p 0: no test, and none of its noise figures computed

    @classmethod
    def of_run(
        cls, robot: Robot, tau: np.ndarray, channels: dict[str, np.ndarray], act: Activity, options: WindowOptions,
    ) -> Stillness:
        """:meth:`of_samples` of a whole run, the ripple floored at the robot's load-cell uncertainty."""
        return cls.of_samples(tau, channels, act.span, options, robot.sensors.load_cell_uncertainty, act)

    def parts(self, act: Activity) -> tuple[np.ndarray, np.ndarray]:
        """Per sample (N,): the kinematic score (ranges over their limits) and the ripple over its tolerance."""
        kin = np.zeros(act.ripple.shape[0])
        for c, r in act.ranges.items():
            np.maximum(kin, (r / self.thresholds[c]).max(axis=1), out=kin)
        return kin, act.ripple / self.ripple_tol

    def judge(self, tau: np.ndarray, channels: dict[str, np.ndarray]) -> tuple[float, float]:
        """The scores of one block of ``span`` consecutive samples (tensions (span, n), channels (span, c)):
        its largest range over the channel's limit and its largest tension standard deviation over the ripple
        tolerance; the numbers :meth:`parts` gives the block's middle sample (index span // 2) of a run."""
        kin = 0.0
        for c, x in channels.items():
            kin = max(kin, float(np.max((x.max(axis=0) - x.min(axis=0)) / self.thresholds[c])))
        return kin, float(tau.std(axis=0).max()) / self.ripple_tol

    def trim(self, tau: np.ndarray, channels: dict[str, np.ndarray], min_len: int = 2) -> tuple[int, int]:
        """Samples to cut from the start and the end of a still stretch (tensions (L, n), channels (L, c)) so
        that what is left rests (:meth:`EndsTest.trim`); (0, 0) without an ends test."""
        a, b = (0, 0) if self.ends is None else self.ends.trim(tau, channels, min_len)
        L = tau.shape[0]
        if self.settle is None or L - a - b < min_len:
            return a, b
        c, d = self.settle.trim(tau[a : L - b], {k: x[a : L - b] for k, x in channels.items()}, min_len)
        return a + c, b + d

    def still(self, tau: np.ndarray, channels: dict[str, np.ndarray]) -> bool:
        """Whether a block of ``span`` samples is still: both scores of :meth:`judge` <= 1."""
        kin, ripple = self.judge(tau, channels)
        return kin <= 1.0 and ripple <= 1.0


def settle_test(tau: np.ndarray, channels: dict[str, np.ndarray], span: int, options: WindowOptions) -> SettleTest:
    """The settle test of a run (:class:`calib.selfcal.settle.SettleTest`) with the options' block length,
    false-alarm probability and encoder floors, for a span of ``span`` samples of ``options.span_s``."""
    q = int(round(options.settle_block_s / (options.span_s / span)))
    tols = {"length": options.length_tol, "swivel": options.swivel_tol}
    return SettleTest.of_samples(tau, channels, q, options.settle_test_p, tols, options.settle_tail)


def still_channels(dl: np.ndarray, dsigma: np.ndarray, roll: np.ndarray, pitch: np.ndarray) -> dict[str, np.ndarray]:
    """The kinematic channels the stillness test watches: lengths (N, n) m, swivels (N, n) rad and tilt
    (N, 2) = roll, pitch rad."""
    return {"length": dl, "swivel": dsigma, "tilt": np.stack([roll, pitch], axis=-1)}


def span_samples(options: WindowOptions, dt: float) -> int:
    """Samples in the stillness span for a sample period dt (s): at least 3."""
    return max(3, int(round(options.span_s / dt)))


def min_samples(options: WindowOptions, dt: float) -> int:
    """Consecutive still samples a window needs for a sample period dt (s): at least 2."""
    return max(2, int(math.ceil(options.min_duration_s / dt)))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def _grow(seg: np.ndarray, i0: int, w: int) -> tuple[int, int]:
    """The stretch around seg's minimum i0 where the score stays within 1.5 times it (at least w samples)."""
    ok = seg <= max(1.0, 1.5 * seg[i0])
    x = y = i0
    while x > 0 and ok[x - 1]:
        x -= 1
    while y < len(seg) - 1 and ok[y + 1]:
        y += 1
    if y - x + 1 < w:
        x, y = max(0, i0 - w // 2), min(len(seg) - 1, i0 + w // 2)
    return x, y


def _merge_same(wins: list[Window], tau: np.ndarray, dl: np.ndarray, still: Stillness) -> list[Window]:
    """One window for consecutive windows at the same equilibrium: mean tensions within three ripple
    tolerances, mean lengths within the length range, and the tensions in between within 10 % of them."""
    out: list[Window] = []
    for win in wins:
        if out:
            prev = out[-1]
            a, b = tau[prev.slice].mean(0), tau[win.slice].mean(0)
            gap = tau[prev.last + 1 : win.first]
            same = (np.max(np.abs(a - b)) <= 3.0 * still.ripple_tol
                    and np.all(np.abs(dl[prev.slice].mean(0) - dl[win.slice].mean(0)) <= still.thresholds["length"])
                    and (gap.size == 0 or np.max(np.linalg.norm(gap - a, axis=1)) <= 0.1 * np.linalg.norm(a)))
            if same:
                out[-1] = Window(prev.first, win.last, quasi=prev.quasi and win.quasi)
                continue
        out.append(win)
    return out


def _rest_only(wins: list[Window], tau: np.ndarray, ch: dict[str, np.ndarray], still: Stillness,
               min_len: int, margins: tuple[int, int] = (0, 0)) -> list[Window]:
    """The windows with the ends that still move cut off (:meth:`Stillness.trim`) and ``margins`` samples more
    from the head and the tail; a window left shorter than ``min_len`` samples is dropped."""
    out = []
    for win in wins:
        s = win.slice
        a, b = still.trim(tau[s], {c: x[s] for c, x in ch.items()}, min_len)
        # a run that starts (ends) at rest has no move before (after) that window to cut
        a += margins[0] if win.first > 0 else 0
        b += margins[1] if win.last < tau.shape[0] - 1 else 0
        if win.size - a - b >= min_len:
            out.append(Window(win.first + a, win.last - b, win.setpoint, win.quasi))
    return out


def _align(dist: np.ndarray, tol: float, size: np.ndarray) -> list[int]:
    """Order-keeping assignment of windows (rows, ``size`` samples each) to setpoints (columns): the most
    matches within ``tol``, then the most samples (of the still stretches at one setpoint the longest: the
    platform's rest, where the earlier short ones are the flat spots of a swing after the move), then the
    smallest total distance; per window the setpoint index or -1."""
    m, k = dist.shape
    longest = 1e-3 * np.asarray(size, float)[:, None] / max(float(np.sum(size)), 1.0)
    gain = np.where(dist <= tol, 1.0 + longest + 1e-6 / (m + 1) * (1.0 - dist / tol), -np.inf)
    best = np.zeros((m + 1, k + 1))
    for i in range(1, m + 1):
        for j in range(1, k + 1):
            best[i, j] = max(best[i - 1, j], best[i, j - 1], best[i - 1, j - 1] + gain[i - 1, j - 1])
    label = [-1] * m
    i, j = m, k
    while i > 0 and j > 0:
        if best[i, j] == best[i - 1, j]:
            i -= 1
        elif best[i, j] == best[i, j - 1]:
            j -= 1
        else:
            label[i - 1] = j - 1
            i, j = i - 1, j - 1
    return label


def _gap_quasi(wins: list[Window], score: np.ndarray, w: int, opt: WindowOptions) -> list[Window]:
    """Without a plan: the stillest stretch of each unusually long gap between windows."""
    if len(wins) < 3:
        return []
    gaps = np.array([b.first - a.last for a, b in zip(wins[:-1], wins[1:], strict=True)])
    limit = opt.gap_factor * float(median(gaps))
    extra = []
    for (a, b), gap in zip(zip(wins[:-1], wins[1:], strict=True), gaps, strict=True):
        lo, hi = a.last + w, b.first - w
        if gap <= limit or hi - lo + 1 < w:
            continue
        seg = score[lo : hi + 1]
        i0 = int(np.argmin(seg))
        if seg[i0] <= opt.quasi_max:
            x, y = _grow(seg, i0, w)
            extra.append(Window(lo + x, lo + y, quasi=True))
    return extra


def _relative(sp: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Relative distances (..., k) of values (..., n) to setpoints (k, n)."""
    return np.linalg.norm(value[..., None, :] - sp, axis=-1) / np.linalg.norm(sp, axis=1)


def _fill_missing(
    sp: np.ndarray, wins: list[Window], tau: np.ndarray, kin: np.ndarray, ripple: np.ndarray, still: Stillness,
    dt: float, min_len: int, opt: WindowOptions,
) -> tuple[list[Window], list[MissingSetpoint]]:
    """For each planned setpoint without a window: the stillest stretch near its tensions, between the
    windows of its neighbours in the plan, as a quasi window; else the reason, one sentence."""
    N, w = tau.shape[0], still.span
    by_sp = {win.setpoint: win for win in wins if win.setpoint >= 0}
    score = np.maximum(kin, ripple)
    extra, missing = [], []
    for j in range(sp.shape[0]):
        if j in by_sp:
            continue
        before = [win.last for s, win in by_sp.items() if s < j]
        after = [win.first for s, win in by_sp.items() if s > j]
        lo, hi = (max(before) + 1 if before else 0), (min(after) - 1 if after else N - 1)
        near = np.zeros(N, bool)
        near[lo : hi + 1] = _relative(sp[j : j + 1], tau[lo : hi + 1])[:, 0] <= opt.setpoint_tol
        idx = np.flatnonzero(near)
        if idx.size == 0:
            why = ("the log ends before its tensions were reached" if hi == N - 1 and not after else
                   f"the tensions never came within {100 * opt.setpoint_tol:.0f} % of it")
            missing.append(MissingSetpoint(j, f"setpoint {j}: {why}."))
            continue
        seg = np.where(near, score, np.inf)[lo : hi + 1]
        i0 = int(np.argmin(seg))
        if seg[i0] <= opt.quasi_max:
            x, y = _grow(seg, i0, w)
            extra.append(Window(lo + x, lo + y, j, quasi=True))
            by_sp[j] = extra[-1]  # the next setpoints' search starts after it
            continue
        at_end = idx[-1] >= N - 1 - w and (N - idx[0]) < min_len
        if at_end:
            why = f"the log ends {(N - idx[0]) * dt:.1f} s after its tensions were reached"
        elif float(np.min(kin[idx])) <= 1.0:
            r = float(np.min(ripple[idx])) * still.ripple_tol
            why = f"the tension ripple stayed at {r:.2f} N or more, above the {still.ripple_tol:.2f} N tolerance"
        else:
            why = (f"the platform never came to rest (its stillest stretch moved "
                   f"{float(np.min(kin[idx])):.1f} x the stillness thresholds)")
        missing.append(MissingSetpoint(j, f"setpoint {j}: {why}."))
    return extra, missing


def search_windows(
    robot: Robot,
    t: np.ndarray,
    tau: np.ndarray,
    dl: np.ndarray,
    dsigma: np.ndarray,
    roll: np.ndarray,
    pitch: np.ndarray,
    tau_ref: np.ndarray | None = None,
    setpoints: np.ndarray | None = None,
    options: WindowOptions | None = None,
) -> WindowSearch:
    """Equilibrium windows of a run (arrays (N,) or (N, n), SI units), see the module docstring."""
    opt = options or WindowOptions()
    N = dl.shape[0]
    dt = float(median(np.diff(t))) if N > 1 else 1.0
    ch = still_channels(dl, dsigma, roll, pitch)
    w = span_samples(opt, dt)
    act = Activity.of(tau, ch, w)
    still = Stillness.of_run(robot, tau, ch, act, opt)
    kin, ripple = still.parts(act)
    score = np.maximum(kin, ripple)
    min_len = min_samples(opt, dt)
    wins = [Window(a, b) for a, b in _runs(score <= 1.0) if b - a + 1 >= min_len]
    margins = (0, 0) if still.settle is None else (int(round(opt.settle_margin_s / dt)),
                                                    int(round(opt.settle_tail_margin_s / dt)))
    stretches = _merge_same(wins, tau, dl, still)  # what the ranges call still; the gaps between them moved
    wins = _rest_only(stretches, tau, ch, still, min_len, margins)
    sp = None if setpoints is None or not len(setpoints) else np.asarray(setpoints, dtype=float)
    if sp is None:
        if tau_ref is not None and N:
            away = np.flatnonzero(np.max(np.abs(tau_ref - tau_ref[0]), axis=1) > opt.pretension_band)
            if away.size:
                wins = [win for win in wins if win.last >= away[0] + w] or wins
        wins = sorted(wins + _gap_quasi(stretches, score, w, opt), key=lambda c: c.first)
        return WindowSearch(wins, list(wins), 0, [], still.thresholds, still.ripple_tol, still.ends)
    dist = np.full((len(wins), sp.shape[0]), np.inf)
    for i, win in enumerate(wins):
        dist[i] = _relative(sp, tau[win.slice].mean(axis=0))
        if tau_ref is not None:
            dist[i] = np.minimum(dist[i], _relative(sp, tau_ref[win.slice].mean(axis=0)))
    labels = _align(dist, opt.setpoint_tol, np.array([w_.size for w_ in wins])) if wins else []
    wins = [Window(win.first, win.last, j, win.quasi) for win, j in zip(wins, labels, strict=True)]
    extra, missing = _fill_missing(sp, wins, tau, kin, ripple, still, dt, min_len, opt)
    found = sorted(wins + extra, key=lambda c: c.first)
    used = [win for win in found if win.setpoint >= 0 or opt.use_unmatched]
    return WindowSearch(found, used, sp.shape[0], missing, still.thresholds, still.ripple_tol, still.ends)


def find_windows(
    robot: Robot,
    t: np.ndarray,
    tau: np.ndarray,
    dl: np.ndarray,
    dsigma: np.ndarray,
    roll: np.ndarray,
    pitch: np.ndarray,
    tau_ref: np.ndarray | None = None,
    setpoints: np.ndarray | None = None,
    options: WindowOptions | None = None,
) -> list[Window]:
    """The equilibrium windows a solve uses, in time order (:func:`search_windows`)."""
    return search_windows(robot, t, tau, dl, dsigma, roll, pitch, tau_ref, setpoints, options).used
