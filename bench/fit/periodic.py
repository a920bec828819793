"""Is there a periodic component in a residual's block means, beyond what its noise makes?

A periodogram peak is only evidence of a periodic component when

1. it is significant against the noise the residual is known to carry: under white + flicker (1/f)
   + random-walk noise the low frequencies hold far more power than under white noise, so each
   frequency's power is referred to its own expectation under the noise model's covariance of the
   block means (a red-noise null), not to the periodogram's average (Fisher's g test, white null);
2. it is resolved: at least two periods fit in the span the blocks cover (an outage keeps its
   length), so the period searched is at most half the span;
3. a sine explains the block means better than slow structure with as many parameters does: a
   cubic in time (three coefficients, as the sine's amplitude, phase and frequency) -- a wave longer
   than the record, a trend or a bend is not a period.

Per frequency k / span (k = 2 .. span/2 blocks) the power is P_k = u' G^-1 u with u the centred cosine
and sine columns' products with the means and G their Gram matrix; under the null it is a quadratic
form lam_1 chi2_1 + lam_2 chi2_1 whose weights are the eigenvalues of G^-1 X'CX (C the null
covariance of the centred means).  Each P_k gets its tail probability (Pearson's three moments, exact
when the two weights are equal), and the smallest is corrected for the number of frequencies
searched (Sidak).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2

from bench.fit.noisefloor import centred


def _two_term_sf(q: np.ndarray, l1: np.ndarray, l2: np.ndarray) -> np.ndarray:
    """P(l1 chi2_1 + l2 chi2_1 > q) by Pearson's three-moment approximation (exact for l1 = l2)."""
    c1, c2, c3 = l1 + l2, l1 ** 2 + l2 ** 2, l1 ** 3 + l2 ** 3
    with np.errstate(invalid="ignore", divide="ignore"):
        df = np.where(c3 > 0, c2 ** 3 / np.maximum(c3 ** 2, 1e-300), 2.0)
        x = df + (q - c1) * np.sqrt(2.0 * df) / np.sqrt(2.0 * np.maximum(c2, 1e-300))
    return np.where(c2 > 0, chi2.sf(x, df), 1.0)


def periodic_component(means: np.ndarray, index: np.ndarray, null_cov: np.ndarray,
                       block_s: float = 100.0) -> dict[str, Any]:
    """The strongest resolved periodic component of block ``means`` taken at block numbers ``index``
    (gaps keep their lags), tested against ``null_cov``, the noise model's (generalised) covariance of
    those means.  Returns peak_p (Sidak-corrected), peak_period_s, peak_amplitude_dph and
    better_than_cubic (the fitted sine leaves less than a cubic in time); {} when the span holds fewer
    than four candidate frequencies."""
    y = np.asarray(means, dtype=np.float64)
    idx = np.asarray(index, dtype=np.float64)
    n = len(y)
    span_blocks = int(round(idx[-1] - idx[0])) + 1 if n else 0
    ks = np.arange(2, span_blocks // 2 + 1)
    if n < 6 or len(ks) < 4:
        return {}
    tt = (idx - idx[0]) * block_s
    span = span_blocks * block_s
    yc = y - y.mean()
    c = centred(null_cov)
    ph = 2.0 * np.pi * np.outer(tt, ks / span)
    cs, sn = np.cos(ph), np.sin(ph)
    cs -= cs.mean(axis=0)
    sn -= sn.mean(axis=0)
    g11, g12, g22 = np.sum(cs * cs, 0), np.sum(cs * sn, 0), np.sum(sn * sn, 0)
    det_g = g11 * g22 - g12 ** 2
    ok = det_g > 1e-9 * np.maximum(g11 * g22, 1e-300)
    uc, us = cs.T @ yc, sn.T @ yc
    with np.errstate(invalid="ignore", divide="ignore"):
        power = (g22 * uc ** 2 - 2 * g12 * uc * us + g11 * us ** 2) / det_g
        ccs, csn = c @ cs, c @ sn
        a11, a12, a22 = np.sum(cs * ccs, 0), np.sum(cs * csn, 0), np.sum(sn * csn, 0)
        # eigenvalues of G^-1 A (2 x 2): from its trace and determinant
        tr = (g22 * a11 - 2 * g12 * a12 + g11 * a22) / det_g
        dt = (a11 * a22 - a12 ** 2) / det_g
        disc = np.sqrt(np.maximum(tr ** 2 / 4 - dt, 0.0))
        l1, l2 = np.maximum(tr / 2 + disc, 0.0), np.maximum(tr / 2 - disc, 0.0)
    p_k = np.where(ok, _two_term_sf(power, l1, l2), 1.0)
    m = int(ok.sum())
    if m < 4:
        return {}
    best = int(np.argmin(np.where(ok, p_k, np.inf)))
    p = float(-np.expm1(m * np.log1p(-min(float(p_k[best]), 1.0 - 1e-16))))

    def sine_ssr(freq: float) -> tuple[float, float]:
        basis = np.column_stack([np.ones(n), np.cos(2 * np.pi * freq * tt), np.sin(2 * np.pi * freq * tt)])
        coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
        return float(np.sum((y - basis @ coef) ** 2)), float(np.hypot(coef[1], coef[2]))

    df = 1.0 / span
    f0 = ks[best] * df
    fit = minimize_scalar(lambda f: sine_ssr(f)[0], bounds=(max(f0 - df, 2.0 * df), f0 + df), method="bounded")
    ssr_sine, amp = sine_ssr(float(fit.x))
    u = tt / span - 0.5
    poly = np.column_stack([np.ones(n), u, u ** 2, u ** 3])
    coef, *_ = np.linalg.lstsq(poly, y, rcond=None)
    ssr_cubic = float(np.sum((y - poly @ coef) ** 2))
    return {"peak_p": p, "peak_period_s": float(1.0 / fit.x), "peak_amplitude_dph": amp,
            "better_than_cubic": bool(ssr_sine < ssr_cubic), "frequencies_searched": m}
