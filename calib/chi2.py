"""The chi-square distribution's upper tail and its inverse with the math module alone.

A solve needs a chi2 p-value (``calib.selfcal.result.sigma_scale``) and, with the window-ends test, a chi2
quantile; scipy.special's import costs a command ~0.15 s, more than the solve itself. For dof degrees of freedom
P(X > x) = Q(dof/2, x/2), the regularized upper incomplete gamma function, computed as in Numerical Recipes
(section 6.2): its series below a + 1, the continued fraction of Q (modified Lentz) above. The prefactor
x^a e^-x / Gamma(a) is written sqrt(a / 2 pi) exp(a (log t - t + 1) - stirlerr(a)) with t = x / a, so that no
two large logarithms cancel. Agrees with scipy.stats.chi2 to 1e-12 relative (tests/test_cli_imports.py).
"""

from __future__ import annotations

import math

_EPS = 1e-17  # relative size of the last term / factor kept (below the double's rounding)
_TINY = 1e-300  # Lentz's guard against a zero denominator
_MAX_TERMS = 100_000  # the series and the fraction need O(sqrt(a)) terms near x = a
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _stirlerr(a: float) -> float:
    """log Gamma(a + 1) - ((a + 0.5) log a - a + log sqrt(2 pi)): Stirling's series beyond 10, where it is exact
    to rounding, so that the prefactor of a large a keeps its relative accuracy."""
    if a < 10.0:
        return math.lgamma(a + 1.0) - (a + 0.5) * math.log(a) + a - _LOG_SQRT_2PI
    r = 1.0 / (a * a)
    return (1.0 / 12.0 - r * (1.0 / 360.0 - r * (1.0 / 1260.0 - r * (1.0 / 1680.0 - r / 1188.0)))) / a


def _log_prefactor(a: float, x: float) -> float:
    """log(x^a e^-x / Gamma(a)) for x > 0, a > 0."""
    t = x / a
    if 0.5 < t < 2.0:
        d = (x - a) / a
        core = a * (math.log1p(d) - d)  # a (log t - t + 1) without the cancellation near t = 1
    else:
        core = a * (math.log(t) - t + 1.0)
    return 0.5 * math.log(a) - _LOG_SQRT_2PI + core - _stirlerr(a)


def _lower_series(a: float, x: float) -> float:
    """sum_n x^n / ((a + 1) ... (a + n)), so that P(a, x) = prefactor / a * sum (x < a + 1)."""
    term = total = 1.0
    ap = a
    for _ in range(_MAX_TERMS):
        ap += 1.0
        term *= x / ap
        total += term
        if term < total * _EPS:
            return total
    raise ArithmeticError(f"chi2: the incomplete gamma series did not converge (a = {a}, x = {x})")


def _upper_fraction(a: float, x: float) -> float:
    """The continued fraction h with Q(a, x) = prefactor * h (x >= a + 1), by the modified Lentz method."""
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _MAX_TERMS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < _EPS:
            return h
    raise ArithmeticError(f"chi2: the incomplete gamma fraction did not converge (a = {a}, x = {x})")


def _upper_gamma(a: float, x: float) -> float:
    """Q(a, x), the regularized upper incomplete gamma function, x > 0, a > 0."""
    if x < a + 1.0:
        return 1.0 - math.exp(_log_prefactor(a, x)) / a * _lower_series(a, x)
    log_q = _log_prefactor(a, x)
    if log_q < -800.0:  # far below the smallest double even times the fraction (h < 1/(x + 1 - a) < 1)
        return 0.0
    return math.exp(log_q) * _upper_fraction(a, x)


def chi2_sf(chi2: float, dof: float) -> float:
    """P(X > chi2) of a chi2 with ``dof`` degrees of freedom (scipy.stats.chi2.sf's conventions: 1 at or below
    0, 0 at inf, nan for a nan chi2 or dof <= 0)."""
    chi2, dof = float(chi2), float(dof)
    if not dof > 0 or math.isnan(chi2):
        return math.nan
    if chi2 <= 0:
        return 1.0
    if math.isinf(chi2):
        return 0.0
    return _upper_gamma(0.5 * dof, 0.5 * chi2)


def chi2_pdf(chi2: float, dof: float) -> float:
    """The chi2 density with ``dof`` degrees of freedom at chi2 > 0, 1/unit of chi2."""
    a, x = 0.5 * dof, 0.5 * chi2
    return 0.5 * math.exp(_log_prefactor(a, x)) / x


def chi2_isf(p: float, dof: float) -> float:
    """The chi2 value exceeded with probability p (0 < p < 1), the inverse of :func:`chi2_sf` (scipy's
    ``chi2.isf``; 0 for p = 1, inf for p = 0, nan outside [0, 1] or for dof <= 0): Newton's method on
    log P(X > x), which is close to linear in x in both tails, kept inside a shrinking bracket."""
    p, dof = float(p), float(dof)
    if not dof > 0 or not 0.0 <= p <= 1.0:
        return math.nan
    if p == 1.0:
        return 0.0
    if p == 0.0:
        return math.inf
    lo, hi = 0.0, math.inf
    # Wilson-Hilferty's cube-root normal approximation to start from
    z = _normal_isf(p)
    h = 2.0 / (9.0 * dof)
    x = dof * max(1.0 - h + z * math.sqrt(h), 0.1) ** 3
    target = math.log(p)
    for _ in range(200):
        q = chi2_sf(x, dof)
        if q > p:
            lo = x
        else:
            hi = x
        if q <= 0.0:  # far beyond the tail: come back into the bracket
            x = 0.5 * (lo + hi) if math.isfinite(hi) else 2.0 * x
            continue
        pdf = chi2_pdf(x, dof)
        new = x + (math.log(q) - target) * q / pdf if pdf > 0.0 else math.nan  # d log Q / dx = -pdf / Q
        if abs(new - x) <= 1e-15 * x:  # converged (Newton's last step is below the rounding of x and Q)
            return new
        if not lo < new < hi:  # Newton left the bracket: bisect (doubling while no upper bound is known)
            new = 0.5 * (lo + hi) if math.isfinite(hi) else 2.0 * max(x, lo)
        x = new
    return x


def _normal_isf(p: float) -> float:
    """A standard normal's upper quantile to about 1e-3 (a starting point only): Abramowitz & Stegun 26.2.23."""
    q = min(p, 1.0 - p)
    t = math.sqrt(-2.0 * math.log(q))
    z = t - (2.515517 + t * (0.802853 + t * 0.010328)) / (1.0 + t * (1.432788 + t * (0.189269 + t * 0.001308)))
    return z if p < 0.5 else -z
