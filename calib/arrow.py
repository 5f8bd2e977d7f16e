"""The joint problem's normal equations by blocks (issue 28, :mod:`calib.multirun`): a block-arrow matrix whose
6 x 6 pose blocks meet only their own pose's rows, each eliminated (Schur complement) so that a step, a
gradient and the shared block of the covariance cost one small solve per pose and one per run's theta."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.fitting import Residuals

SINGULAR = 1e-13  # a block whose eigenvalue ratio is below this is singular to working precision (the SVD decides)

_DIAG6 = np.arange(6)


def _by_pose(res: Residuals, k: int, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pose, its entries' (the first ones, ``res.row`` >= 0) 6 pose columns X (k, e_max, 6), theta columns
    T (k, e_max, t) and residuals (k, e_max), zero-padded: a pose's columns meet only its own entries; and the
    entries' positions there (k, e_max; e, the entry count, marks the padding)."""
    row = res.row
    e = int(np.count_nonzero(row >= 0))
    pose = row[:e]
    order = np.argsort(pose, kind="stable")
    counts = np.bincount(pose, minlength=k)
    idx = np.full((k, max(int(counts.max(initial=0)), 1)), e)  # e: the zero row
    idx[pose[order], np.arange(e) - np.repeat(np.cumsum(counts) - counts, counts)] = order
    X = np.vstack([res.A[np.arange(e)[:, None], 6 * pose[:, None] + _DIAG6], np.zeros((1, 6))])
    return X[idx], np.vstack([T[:e], np.zeros((1, T.shape[1]))])[idx], np.concatenate([res.r[:e], [0.0]])[idx], idx


@dataclass
class Arrow:
    """Normal equations of the joint problem by blocks, on unit-norm columns: per run, the pose blocks U
    (k, 6, 6), their coupling W (k, 6, t) with the run's theta columns (own, then shared unless fixed), the
    theta block V (t, t) and the gradients gp (k, 6), gt (t,); the column norms of the joint Jacobian (the
    scale, in :func:`stack`'s column order) and each run's columns there (own, poses)."""

    U: list[np.ndarray]
    W: list[np.ndarray]
    V: list[np.ndarray]
    gp: list[np.ndarray]
    gt: list[np.ndarray]
    scale: np.ndarray
    cols: list[tuple[slice, slice]]
    q: int  # shared columns in the problem (0 when fixed)
    # per run, what J^T r of another residual vector needs: the per-pose column blocks X, the theta
    # columns T (unscaled) and the per-pose order of the entries (:func:`_by_pose`)
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = field(default_factory=list, repr=False)
    pinned: np.ndarray | None = None  # (q,) bool: shared columns held (a bound the step would cross)
    _last: tuple | None = field(default=None, repr=False)  # the reduced matrix of the last damping

    @classmethod
    def of(cls, runs: list[Any], blocks: list[Residuals], q: int, fixed_shared: bool) -> Arrow:
        """From the runs (:class:`calib.multirun.RunFit`: its poses and theta) and their Residuals: a pose's
        columns only meet that pose's rows, so the pose blocks of the
        normal matrix are 6 x 6 (no dense m x (6k + p) product)."""
        qq = 0 if fixed_shared else q
        raw, cols, parts, start = [], [], [], qq
        for rf, res in zip(runs, blocks, strict=True):
            k = rf.poses.shape[0]
            p_own = rf.theta.shape[0] - q
            T = res.A[:, 6 * k:6 * k + p_own + qq]
            X, Tp, rp, idx = _by_pose(res, k, T)
            Xt = X.transpose(0, 2, 1)
            raw.append((Xt @ X, Xt @ Tp, T.T @ T, (Xt @ rp[..., None])[..., 0], T.T @ res.r))
            parts.append((X, T, idx, int(np.count_nonzero(res.row >= 0))))
            cols.append((slice(start, start + p_own), slice(start + p_own, start + p_own + 6 * k)))
            start += p_own + 6 * k
        d2 = np.zeros(start)
        for (U, _, V, _, _), (so, sp) in zip(raw, cols, strict=True):
            d2[sp] = np.diagonal(U, axis1=1, axis2=2).ravel()
            p_own = so.stop - so.start
            d2[so] = np.diag(V)[:p_own]
            d2[:qq] += np.diag(V)[p_own:]
        scale = np.sqrt(d2)
        scale[scale == 0] = 1.0
        out = cls([], [], [], [], [], scale, cols, qq, parts)
        for (U, W, V, gp, gt), (so, sp) in zip(raw, cols, strict=True):
            sp_, st = scale[sp].reshape(-1, 6), np.concatenate([scale[so], scale[:qq]])
            out.U.append(U / (sp_[:, :, None] * sp_[:, None, :]))
            out.W.append(W / (sp_[:, :, None] * st[None, None, :]))
            out.V.append(V / np.outer(st, st))
            out.gp.append(gp / sp_)
            out.gt.append(gt / st)
        return out

    @functools.cached_property
    def _fixed(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per run, what every damping's step shares: the pose blocks' diagonals (floored) and V's diagonal."""
        return [(np.maximum(np.diagonal(U, axis1=1, axis2=2), 1e-12), np.diag(V).copy()) for U, V in
                zip(self.U, self.V, strict=True)]

    def gradient(self, rs: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """J^T r on the scaled columns, by blocks (pose gp (k, 6), theta gt (t,) per run), of other residual
        vectors rs (one per run, in the order of the runs' Residuals)."""
        gps, gts = [], []
        for (X, T, idx, e), r, (so, sp) in zip(self.parts, rs, self.cols, strict=True):
            rp = np.concatenate([r[:e], [0.0]])[idx]
            sp_, st = self.scale[sp].reshape(-1, 6), np.concatenate([self.scale[so], self.scale[:self.q]])
            gps.append(np.einsum("kei,ke->ki", X, rp) / sp_)
            gts.append((T.T @ r) / st)
        return gps, gts

    def step(self, damping: float, grads: tuple[list, list] | None = None) -> tuple[np.ndarray, float]:
        """The step ds (scaled columns) solving (N + damping diag(N)) ds = -g by eliminating each run's pose
        blocks (a Schur complement on [shared, own_1, own_2, ...]), and the decrease -(2 g.ds + ds.N.ds) the
        undamped quadratic model predicts for it. ``grads``: another g (:meth:`gradient`) than the residuals'
        (the geodesic acceleration's right-hand side)."""
        gps, gts = (self.gp, self.gt) if grads is None else grads
        M, rhs, parts = self._reduced(damping, gps, gts)
        x = -np.linalg.solve(M, rhs)
        qq = self.q
        ds = np.zeros(self.scale.shape[0])
        ds[:qq] = x[:qq]
        gain = 0.0
        for (so, sp), (idx, Y, y), U, W, V, gp, gt in zip(self.cols, parts, self.U, self.W, self.V, gps, gts,
                                                          strict=True):
            dt = x[idx]
            dp = -(y + Y @ dt)
            ds[so], ds[sp] = dt[:so.stop - so.start], dp.ravel()
            Ud = (U @ dp[..., None])[..., 0]
            quad = float(np.sum(dp * Ud) + 2.0 * np.sum(dp * (W @ dt)) + dt @ V @ dt)
            gain -= 2.0 * (float(np.sum(gp * dp)) + float(gt @ dt)) + quad
        return ds, gain

    def covariance(self) -> tuple[np.ndarray, int] | None:
        """The shared block of N's inverse (scaled columns) and N's rank from the inverse of the Schur
        complement on [shared, own_1, ...]; None when a pose block or it is singular (the caller's SVD decides)."""
        def singular(a: np.ndarray) -> bool:
            ev = np.linalg.eigvalsh(a)
            return bool(a.size and np.any(ev[..., 0] <= SINGULAR * np.maximum(ev[..., -1], 1e-300)))

        if any(singular(U) for U in self.U):  # before the reduction, which inverts them undamped
            return None
        M, _, _ = self._reduced(0.0, pins=False)
        if singular(M[None]):
            return None
        q = self.q
        cov = np.linalg.solve(M, np.eye(M.shape[0])[:, :q])[:q] if q else np.zeros((0, 0))
        return cov, int(self.scale.shape[0])

    def _reduced(self, damping: float, gps: list | None = None, gts: list | None = None, pins: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, list]:
        """The damped system reduced to [shared, own_1, own_2, ...] (each run's pose blocks eliminated), its
        right-hand side (of the gradient gps, gts; None: the residuals'), and per run what the poses'
        back-substitution needs (indices in it, Y, y). ``pins``: the held shared columns (``pinned``) get no
        step. The reduced matrix of the last damping is kept (the geodesic acceleration's second solve)."""
        gps = self.gp if gps is None else gps
        gts = self.gt if gts is None else gts
        M, facs, at = self._factor(damping, pins)
        qq = self.q
        rhs = np.zeros(at[-1])
        parts = []
        for j, (W, gp, gt, (Ui, Y)) in enumerate(zip(self.W, gps, gts, facs, strict=True)):
            y = (Ui @ gp[..., None])[..., 0]
            rr = gt - W.reshape(-1, W.shape[2]).T @ y.ravel()
            o, no = slice(at[j], at[j + 1]), at[j + 1] - at[j]  # the run's own block, then the shared one
            rhs[o] += rr[:no]
            rhs[:qq] += rr[no:]
            parts.append((np.concatenate([np.arange(at[j], at[j + 1]), np.arange(qq)]), Y, y))
        if pins and self.pinned is not None:
            rhs[np.flatnonzero(self.pinned)] = 0.0
        return M, rhs, parts

    def _factor(self, damping: float, pins: bool) -> tuple[np.ndarray, list, np.ndarray]:
        """The reduced matrix at this damping, per run the inverse damped pose blocks and Y = U_d^-1 W, and
        the reduced columns' offsets (cached for the last damping)."""
        key = (damping, pins and self.pinned is not None and bool(self.pinned.any()))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        qq = self.q
        own = [so.stop - so.start for so, _ in self.cols]
        at = np.cumsum([qq, *own])
        M, dg, facs = np.zeros((at[-1], at[-1])), np.zeros(at[-1]), []
        for j, (U, W, V, (dU, dV)) in enumerate(zip(self.U, self.W, self.V, self._fixed, strict=True)):
            Ud = U.copy()
            Ud[:, _DIAG6, _DIAG6] += damping * dU
            Ui = np.linalg.inv(Ud)
            Y = Ui @ W
            t = W.shape[2]
            S = V - W.reshape(-1, t).T @ Y.reshape(-1, t)
            o, no = slice(at[j], at[j + 1]), at[j + 1] - at[j]
            M[o, o] += S[:no, :no]
            M[o, :qq] += S[:no, no:]
            M[:qq, o] += S[no:, :no]
            M[:qq, :qq] += S[no:, no:]
            dg[o] += dV[:no]
            dg[:qq] += dV[no:]
            facs.append((Ui, Y))
        M[range(at[-1]), range(at[-1])] += damping * np.maximum(dg, 1e-12)
        if key[1]:  # held columns: no step, the others without them
            i = np.flatnonzero(self.pinned)
            M[i, :], M[:, i] = 0.0, 0.0
            M[i, i] = 1.0
        self._last = (key, (M, facs, at))
        return M, facs, at
