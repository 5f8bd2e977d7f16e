"""The NWLS problem of Zoffoli eq. 13-17 as global parameters plus per-pose blocks (a block-arrow Jacobian).

Unknowns: theta (p,) = [zeta_0, extra effect parameters] and one pose zeta_i (6,) per measurement row.
Residual of row i: w * (prediction(zeta_i, theta) - reading_i), with w = 1/sigma per channel (eq. 17).
The rows whose tensions are given are static (tension channel included), the others kinematic. The reference
row (the reading at zeta_0 itself) contributes, where given, its absolute tensions and roll/pitch; its
relative readings are zero by construction and carry no information. Parameters with a Gaussian prior (a
model's ``priors()``, e.g. a device's accuracy class) add one pseudo-reading each, (theta_j - mean_j) / sd_j,
after the reference row: a residual and a parameter more, so the degrees of freedom do not change.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from calib.selfcal.model import CHANNELS, ChannelPrediction, MeasurementModel, channel_width


@dataclass
class Measurements:
    """Readings at k measurement rows, relative sensors taken relative to the reference sample.

    tau (k, n) N, NaN rows where tensions are not used (kinematic rows); dl (k, n) m; dsigma (k, n) rad;
    orientation (k, 3): roll, pitch (absolute) and yaw minus the reference yaw, rad.
    ref_tau (n,) and ref_orientation (2,) are the absolute readings at the reference sample (NaN: unused).
    samples (k,) and windows (k, 2) say where each row comes from in the run (-1 when not applicable);
    times (k,) when each row was read, s after the reference sample (None: unknown).
    approach (k, n): per row and cable, the direction the cable last moved before the row's window, +1 paid
    out (length grew), -1 reeled in, 0 unknown; load_approach (k, n): the same for the tension the load
    cell last saw change (+1 rising, -1 falling); ref_approach and ref_load_approach (n,) the same at the
    reference sample. swivel_approach (k, n) and ref_swivel_approach (n,): the way each swivel angle last
    turned (+1 its reading grew, -1 fell). None (the default, e.g. rows of old callers) means unknown
    everywhere: the direction-dependent effects (pulley friction, load-cell hysteresis, swivel friction) then
    see no direction. held_tau (k, n) N: where finite, the tension each row's cable is held at (a sample of a
    force-controlled hold: the platform sways at that tension), which the model uses in place of the statics'
    at the row's pose (calib.selfcal.model.held_tensions); None: the statics' everywhere.
    """

    tau: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    orientation: np.ndarray
    ref_tau: np.ndarray
    ref_orientation: np.ndarray
    samples: np.ndarray | None = None
    windows: np.ndarray | None = None
    times: np.ndarray | None = None
    approach: np.ndarray | None = None
    load_approach: np.ndarray | None = None
    ref_approach: np.ndarray | None = None
    ref_load_approach: np.ndarray | None = None
    swivel_approach: np.ndarray | None = None
    ref_swivel_approach: np.ndarray | None = None
    held_tau: np.ndarray | None = None

    @property
    def k(self) -> int:
        return int(self.dl.shape[0])

    @property
    def static(self) -> np.ndarray:
        return np.all(np.isfinite(self.tau), axis=1)

    def channel(self, name: str) -> np.ndarray:
        return {"tension": self.tau, "length": self.dl, "swivel": self.dsigma, "orientation": self.orientation}[
            name
        ]


@dataclass
class Group:
    """Rows sharing one set of channels: indices into the pose array, readings and weights (kg, m)."""

    idx: np.ndarray
    channels: tuple[str, ...]
    reading: np.ndarray
    weight: np.ndarray
    slices: dict[str, slice] = field(default_factory=dict)


@dataclass
class Evaluation:
    """Weighted residuals and their derivatives: per group r (kg, m), J (kg, m, 6), G (kg, m, p); reference
    row r0 (m0,), G0 (m0, p)."""

    groups: list[tuple[Group, np.ndarray, np.ndarray | None, np.ndarray | None]]
    r0: np.ndarray
    g0: np.ndarray | None

    @property
    def cost(self) -> float:
        return 0.5 * (sum(float(np.sum(r * r)) for _, r, _, _ in self.groups) + float(self.r0 @ self.r0))


@dataclass
class Observed:
    """The observed entries of a problem's residuals in a fixed order: per group, by channel and component,
    their flat positions in the group's (rows, readings) array (e,) and weights (e,); then the reference
    row's observed entries (``ref``,
    indices into r0's first ``n_ref``) and the priors; their labels per entry: channel, component, row
    (-1: the reference row, -2: a prior)."""

    groups: list[tuple[np.ndarray, np.ndarray]]
    ref: np.ndarray
    n_ref: int
    channel: np.ndarray
    index: np.ndarray
    row: np.ndarray
    pose_cols: np.ndarray  # (e, 6): the pose columns of each row entry (the first e entries)


class Problem:
    """Residuals of eq. 13 weighted as eq. 17 for a measurement model and readings.

    sigma: per channel, the standard deviation (c,) of one reading (N, m, rad).
    """

    def __init__(self, model: MeasurementModel, meas: Measurements, sigma: dict[str, np.ndarray]):
        self.model = model
        self.meas = meas
        n = model.robot.n
        self.sigma = {c: np.broadcast_to(np.asarray(sigma[c], float), (channel_width(c, n),)) for c in CHANNELS}
        static = meas.static
        self.groups: list[Group] = []
        for mask, chans in ((static, CHANNELS), (~static, CHANNELS[1:])):
            idx = np.flatnonzero(mask)
            if idx.size:
                self.groups.append(self._group(idx, chans))
        # each row's group and its place in it (pose_normal_equations selects rows by these, not by np.isin)
        self._row_group = np.full(meas.k, -1)
        self._row_place = np.zeros(meas.k, dtype=int)
        for j, g in enumerate(self.groups):
            self._row_group[g.idx] = j
            self._row_place[g.idx] = np.arange(g.idx.size)
        ref_chans = []
        ref_read, ref_w = [], []
        if np.all(np.isfinite(meas.ref_tau)):
            ref_chans.append("tension")
            ref_read.append(meas.ref_tau)
            ref_w.append(1.0 / self.sigma["tension"])
        ro = np.asarray(meas.ref_orientation, float)
        ref_chans.append("orientation")
        ref_read.append(np.r_[np.nan_to_num(ro), 0.0])
        ref_w.append(np.r_[np.where(np.isfinite(ro), 1.0 / self.sigma["orientation"][:2], 0.0), 0.0])
        self.ref_channels = tuple(ref_chans)
        self.ref_reading = np.concatenate(ref_read)
        self.ref_weight = np.concatenate(ref_w)
        self.prior_idx, self.prior_mean, self.prior_sd = model.priors()
        q = self.prior_idx.size
        self._prior_jac = np.zeros((q, model.n_params))  # d(prior pseudo-readings)/d theta, constant
        self._prior_jac[np.arange(q), self.prior_idx] = 1.0 / self.prior_sd

    def _group(self, idx: np.ndarray, chans: tuple[str, ...]) -> Group:
        n = self.model.robot.n
        reads, ws, slices, start = [], [], {}, 0
        for c in chans:
            v = self.meas.channel(c)[idx]
            w = np.where(np.isfinite(v), 1.0 / self.sigma[c][None, :], 0.0)
            reads.append(np.nan_to_num(v))
            ws.append(w)
            slices[c] = slice(start, start + channel_width(c, n))
            start += channel_width(c, n)
        return Group(idx, chans, np.concatenate(reads, 1), np.concatenate(ws, 1), slices)

    @property
    def k(self) -> int:
        return self.meas.k

    def _times(self, rows: np.ndarray) -> np.ndarray | None:
        t = self.meas.times
        return None if t is None else np.asarray(t, float)[rows]

    def _approach(self, rows: np.ndarray | None) -> dict[str, np.ndarray]:
        """``{"approach": (m, n, 4)}`` for the rows (None: the reference row): the cable-motion, load and
        swivel directions of each row, then the reference's swivel direction (a relative swivel reading
        carries the reference's state too); empty when the readings carry no directions (older models need
        no keyword)."""
        m = self.meas
        ref_s = m.ref_swivel_approach
        if rows is None:
            parts = [m.ref_approach, m.ref_load_approach, ref_s]
        else:
            parts = [None if a is None else np.asarray(a, float)[rows]
                     for a in (m.approach, m.load_approach, m.swivel_approach)]
        if all(a is None for a in parts):
            return {}
        shape = np.shape(np.atleast_2d(next(a for a in parts if a is not None)))
        parts.append(ref_s)
        out = [np.zeros(shape) if a is None else np.broadcast_to(np.atleast_2d(np.asarray(a, float)), shape)
               for a in parts]
        return {"approach": np.stack(out, axis=-1)}

    def _held(self, rows: np.ndarray, joint: bool = False) -> dict[str, np.ndarray]:
        """``{"held_tension": (m, n)}`` for the rows (the reference row's, NaN, first when ``joint``) where
        the readings hold tensions (:attr:`Measurements.held_tau`); empty otherwise."""
        h = self.meas.held_tau
        if h is None:
            return {}
        h = np.asarray(h, float)[rows]
        return {"held_tension": np.vstack([np.full((1, h.shape[1]), np.nan), h]) if joint else h}

    @functools.cached_property
    def observed(self) -> Observed:
        """Where the observed entries are (fixed by the weights): their order and labels (:class:`Observed`)."""
        per_group, ch, ix, rw = [], [], [], []
        for g in self.groups:
            flat, ws = [], []
            for c in g.channels:
                sl = g.slices[c]
                a, i = np.nonzero(g.weight[:, sl].T > 0)  # component-major: component a, its observed rows
                flat.append(i * g.weight.shape[1] + sl.start + a)
                ws.append(g.weight[i, sl.start + a])
                ch.append(np.full(a.size, c))
                ix.append(a)
                rw.append(g.idx[i])
            per_group.append((np.concatenate(flat), np.concatenate(ws)))
        n = self.model.robot.n
        widths = [channel_width(c, n) for c in self.ref_channels]
        ref_ch = np.repeat(np.array(self.ref_channels), widths) if widths else np.zeros(0, str)
        ref_ix = np.concatenate([np.arange(w) for w in widths]) if widths else np.zeros(0, int)
        ok = np.flatnonzero(self.ref_weight[:ref_ch.size] > 0)
        q = self.prior_idx.size
        ch += [ref_ch[ok], np.full(q, "prior")]  # prior pseudo-readings: channel "prior", row -2
        ix += [ref_ix[ok], np.asarray(self.prior_idx, int)]
        rw += [np.full(ok.size, -1), np.full(q, -2)]
        row = np.concatenate(rw).astype(int)
        pose = row[row >= 0]  # the entries of the rows come first: their pose's columns in a dense Jacobian
        return Observed(per_group, ok, ref_ch.size, np.concatenate(ch).astype(str),
                        np.concatenate(ix).astype(int), row, 6 * pose[:, None] + np.arange(6))

    @property
    def n_residuals(self) -> int:
        """Number of residuals with a non-zero weight."""
        return int(sum(np.count_nonzero(g.weight) for g in self.groups) + np.count_nonzero(self.ref_weight)
                   + self.prior_idx.size)

    @property
    def single(self) -> bool:
        """One group of rows whose channels include the reference row's (one model call per evaluation)."""
        return len(self.groups) == 1 and set(self.ref_channels) <= set(self.groups[0].channels)

    def evaluate(self, theta: np.ndarray, poses: np.ndarray, derivatives: bool = True,
                 physical: tuple | None = None) -> Evaluation:
        """Weighted residuals (and Jacobian blocks) at theta (p,) and poses (k, 6). The reference pose is
        predicted in the same model call as the first group whose channels include its own (one call less
        per evaluation: the diagnosis's refits spend most of their time in these calls). ``physical``
        (a :attr:`single` problem of an EffectModel): the model's ``physical(theta, [zeta_0; poses; zeta_0])``
        already computed (:mod:`calib.multirun` computes it for several runs at once)."""
        if physical is not None and not self.single:
            raise ValueError("precomputed physical quantities need a problem with one group of rows")
        out = []
        pred0 = None
        for g, (joint, times, extra) in zip(self.groups, self._group_inputs, strict=True):
            z = poses[g.idx]
            if joint:
                z = np.vstack([theta[None, :6], z])
                if physical is not None:
                    extra = {**extra, "physical": physical}
            pred = self.model.predict(z, theta, g.channels, times, **extra)
            if joint:
                pred0 = {c: _take(pred[c], slice(0, 1)) for c in self.ref_channels}
                pred = {c: _take(pred[c], slice(1, None)) for c in g.channels}
            val = np.concatenate([pred[c].value for c in g.channels], 1)
            r = g.weight * (val - g.reading)
            if derivatives:
                J = g.weight[..., None] * np.concatenate([pred[c].d_pose for c in g.channels], 1)
                G = g.weight[..., None] * np.concatenate([pred[c].d_theta for c in g.channels], 1)
            else:
                J = G = None
            out.append((g, r, J, G))
        if pred0 is None:
            pred0 = self.model.predict(theta[None, :6], theta, self.ref_channels, np.zeros(1),
                                       **self._approach(None))
        val0 = np.concatenate([pred0[c].value[0] for c in self.ref_channels])
        r0 = self.ref_weight * (val0 - self.ref_reading)
        g0 = None
        if derivatives:
            g0 = np.concatenate([pred0[c].d_theta[0] for c in self.ref_channels], 0)
            g0[:, :6] += np.concatenate([pred0[c].d_pose[0] for c in self.ref_channels], 0)
            g0 = self.ref_weight[:, None] * g0
        if self.prior_idx.size:
            r0 = np.concatenate([r0, (theta[self.prior_idx] - self.prior_mean) / self.prior_sd])
            if derivatives:
                g0 = np.vstack([g0, self._prior_jac])
        return Evaluation(out, r0, g0)

    @functools.cached_property
    def _group_inputs(self) -> list[tuple[bool, np.ndarray | None, dict[str, np.ndarray]]]:
        """Per group: whether the reference row is predicted with it (the first group whose channels include
        the reference row's), and the rows' times and directions for the model (the reference row's first
        when joint); fixed by the readings."""
        out, joint_done = [], False
        for g in self.groups:
            times, extra = self._times(g.idx), self._approach(g.idx)
            joint = not joint_done and set(self.ref_channels) <= set(g.channels)
            if joint:
                joint_done = True
                times = None if times is None else np.r_[0.0, times]
                extra = self._joint_approach(self._approach(None), extra, g.idx.size)
            out.append((joint, times, extra | self._held(g.idx, joint)))
        return out

    def _joint_approach(self, ref: dict, rows: dict, m: int) -> dict[str, np.ndarray]:
        """The directions of the reference row stacked on those of m rows (zeros where one side has none)."""
        if not ref and not rows:
            return {}
        n = self.model.robot.n
        a = ref.get("approach", np.zeros((1, n, 4))).reshape(1, n, 4)
        b = rows.get("approach", np.zeros((m, n, 4))).reshape(m, n, 4)
        return {"approach": np.concatenate([a, b], axis=0)}

    def pose_normal_equations(
        self, theta: np.ndarray, poses: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For the given rows only, with theta fixed: cost 0.5|r_i|^2 (m,), J_i^T J_i (m, 6, 6), J_i^T r_i (m, 6);
        poses (m, 6) are the poses of those rows."""
        m = rows.shape[0]
        cost, U, b = np.zeros(m), np.zeros((m, 6, 6)), np.zeros((m, 6))
        in_group = self._row_group[rows]
        for j, g in enumerate(self.groups):
            sel = np.flatnonzero(in_group == j)
            if not sel.size:
                continue
            pos = self._row_place[rows[sel]]
            pred = self.model.predict(poses[sel], theta, g.channels, self._times(rows[sel]),
                                      **self._approach(rows[sel]), **self._held(rows[sel]))
            w = g.weight[pos]
            r = w * (np.concatenate([pred[c].value for c in g.channels], 1) - g.reading[pos])
            J = w[..., None] * np.concatenate([pred[c].d_pose for c in g.channels], 1)
            Jt = J.transpose(0, 2, 1)
            cost[sel] = 0.5 * np.sum(r * r, axis=1)
            U[sel] = Jt @ J
            b[sel] = (Jt @ r[..., None])[..., 0]
        return cost, U, b

    def channel_residuals(
        self, theta: np.ndarray, poses: np.ndarray, ev: Evaluation | None = None
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per channel, the unweighted residuals (SI) and the normalised ones (divided by sigma), observed
        entries only (flattened); ``ev``: the evaluation at theta and poses if already computed."""
        if ev is None:
            ev = self.evaluate(theta, poses, derivatives=False)
        si: dict[str, list[np.ndarray]] = {c: [] for c in CHANNELS}
        nz: dict[str, list[np.ndarray]] = {c: [] for c in CHANNELS}
        for g, r, _, _ in ev.groups:
            for c in g.channels:
                w = g.weight[:, g.slices[c]]
                rr = r[:, g.slices[c]]
                ok = w > 0
                nz[c].append(rr[ok])
                si[c].append(rr[ok] / w[ok])
        start = 0
        n = self.model.robot.n
        for c in self.ref_channels:
            sl = slice(start, start + channel_width(c, n))
            start = sl.stop
            w, rr = self.ref_weight[sl], ev.r0[sl]
            ok = w > 0
            nz[c].append(rr[ok])
            si[c].append(rr[ok] / w[ok])
        empty = np.zeros(0)
        return {c: (np.concatenate(si[c] or [empty]), np.concatenate(nz[c] or [empty])) for c in CHANNELS}


def _take(p: ChannelPrediction, rows: slice) -> ChannelPrediction:
    """The rows of a channel prediction (value, d_pose, d_theta)."""
    return ChannelPrediction(p.value[rows], p.d_pose[rows], p.d_theta[rows])
