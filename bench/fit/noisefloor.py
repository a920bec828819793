"""The noise floor of a residual: the std of 100-s means that noise alone would give over a record of
a given length, robust to 1/f (flicker, "bias instability") noise.

Method.  The Allan variance of a residual at short averaging times tau is dominated by the sensor's
noise, not by slow thermal structure.  It is fitted (non-negative least squares on the octave taus
up to ``tau_max``, relative weights by the number of terms) with the IEEE 952 power laws

    sigma^2(tau) = q tau^-2  (quantisation / white phase)  +  w tau^-1 (white rate, ARW)
                 + f tau^0   (flicker, bias instability)    +  k tau^1  (rate random walk)
                 + d tau^2   (slow structure / drift)

The last two terms are nuisance terms, NOT part of the floor: at the short taus used, slow structure
left in the residual (a trend or a slow wave grows as tau^2 there, a wander as tau^1) would otherwise
be read as noise; a genuine rate random walk is invisible at those taus anyway (IEEE 952 levels of
navigation and tactical gyros put it orders of magnitude below white and flicker noise at 100 s).  The expected sample variance of M consecutive tau-means of
a power-law noise sigma^2 ~ tau^mu is its Allan variance times Barnes' bias function

    B1(M, mu) = M (1 - M^mu) / (2 (M - 1) (1 - 2^mu))     (mu != 0),   M ln M / (2 (M - 1) ln 2)  (mu = 0)

so for white noise the floor is ADEV(100 s) itself, while flicker noise makes the std of 100-s means
over a long record larger than ADEV(100 s) (B1 grows like ln M).  The floor for a record of M blocks
of 100 s is sqrt(sum_k h_k 100^mu_k B1(M, mu_k)).

Uncertainty: the std of M block means has chi-square sampling scatter with about
edf = (M - 1) / B1_mix degrees of freedom (B1_mix: the floor's variance-weighted B1; white noise gives
M - 1, flicker far fewer); the reported interval is the central 90 % of noise-only std100 values,
which is what a residual made of noise alone would show on that record.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import nnls
from scipy.stats import chi2

BLOCK_S = 100.0
MUS = (-2.0, -1.0, 0.0, 1.0, 2.0)     # Allan-variance exponents fitted
NOISE_MUS = (-2.0, -1.0, 0.0)          # those that make the floor (tau^1 and tau^2: nuisance terms)
WHITE_MUS = (-2.0, -1.0)
TAU_MAX_S = 1100.0
INTERVAL = 0.90


def barnes_b1(m: float, mu: float) -> float:
    """Barnes' B1(N, mu): ratio of the expected N-sample variance to the Allan (2-sample) variance."""
    m = float(max(m, 2.0))
    if abs(mu) < 1e-12:
        return m * np.log(m) / (2.0 * (m - 1.0) * np.log(2.0))
    return m * (1.0 - m ** mu) / (2.0 * (m - 1.0) * (1.0 - 2.0 ** mu))


@dataclass
class NoiseModel:
    """Allan-variance power-law coefficients of a residual (deg/h units)."""

    coef: dict[float, float]           # mu -> h_mu, sigma^2(tau) = sum h_mu tau^mu
    taus: np.ndarray
    adev: np.ndarray
    tau_max_s: float

    def allan_var(self, tau: float, mus=NOISE_MUS) -> float:
        return float(sum(self.coef.get(mu, 0.0) * tau ** mu for mu in mus))

    def floor(self, record_s: float, block_s: float = BLOCK_S, mus: tuple[float, ...] = NOISE_MUS) -> dict[str, Any]:
        """Expected std of ``block_s`` means over ``record_s`` seconds, with its interval (``mus``: the
        noise terms counted; the white-only floor, ``mus=WHITE_MUS``, is a lower bound)."""
        m = max(2.0, np.floor(record_s / block_s))
        parts = {mu: self.coef.get(mu, 0.0) * block_s ** mu * barnes_b1(m, mu) for mu in mus}
        var = float(sum(parts.values()))
        if var <= 0:
            return {"noise_floor_dph": float("nan"), "interval_dph": [float("nan"), float("nan")], "edf": 0.0,
                    "blocks": int(m)}
        allan_100 = sum(self.coef.get(mu, 0.0) * block_s ** mu for mu in mus)
        b1_mix = var / allan_100 if allan_100 > 0 else 1.0
        edf = max(1.0, (m - 1.0) / max(b1_mix, 1.0))
        lo = np.sqrt(var * chi2.ppf((1 - INTERVAL) / 2, edf) / edf)
        hi = np.sqrt(var * chi2.ppf((1 + INTERVAL) / 2, edf) / edf)
        return {"noise_floor_dph": float(np.sqrt(var)), "interval_dph": [float(lo), float(hi)], "edf": float(edf),
                "blocks": int(m), "adev100_dph": float(np.sqrt(max(allan_100, 0.0))),
                "flicker_share": float(parts.get(0.0, 0.0) / var)}

    def summary(self) -> dict[str, Any]:
        h = self.coef
        return {"white_dph_at_1s": float(np.sqrt(max(h.get(-1.0, 0.0), 0.0))),
                "flicker_adev_dph": float(np.sqrt(max(h.get(0.0, 0.0), 0.0))),
                "quantisation_dph_s": float(np.sqrt(max(h.get(-2.0, 0.0), 0.0))),
                "rate_random_walk_dph_per_rt_s": float(np.sqrt(max(h.get(1.0, 0.0), 0.0))),
                "structure_term_dph_per_s": float(np.sqrt(max(h.get(2.0, 0.0), 0.0))),
                "tau_max_s": float(self.tau_max_s)}


def _oadev_octave(x: np.ndarray, dt: float, tau_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance (``bench.signal.allan_deviation``) at octave multiples of dt up to
    tau_max: (taus, variances, number of terms)."""
    from bench.signal import allan_deviation

    taus = dt * 2.0 ** np.arange(0, int(np.floor(np.log2(max(tau_max / dt, 1.0)))) + 1)
    res = allan_deviation(x, 1.0 / dt, taus=taus)
    return res.taus_s, res.adev ** 2, res.n


def fit_noise_model(residuals: list[tuple[np.ndarray, float]], tau_max_s: float = TAU_MAX_S) -> NoiseModel:
    """Fit the power laws to the pooled Allan variance of one or more residual series (each given
    with its sample period).  Series are pooled per tau, weighted by their number of terms."""
    pooled: dict[float, list[float]] = {}
    for x, dt in residuals:
        x = np.asarray(x, dtype=np.float64)
        x = x[np.isfinite(x)]
        if len(x) < 16:
            continue
        tmax = min(tau_max_s, len(x) * dt / 8.0)
        taus, avar, n = _oadev_octave(x, dt, tmax)
        for tau, v, k in zip(taus, avar, n):
            key = round(float(tau), 6)
            acc = pooled.setdefault(key, [0.0, 0.0])
            acc[0] += v * k
            acc[1] += k
    if not pooled:
        raise ValueError("noise floor: the residual is too short for an Allan deviation")
    taus = np.array(sorted(pooled))
    avar = np.array([pooled[t][0] / pooled[t][1] for t in taus])
    counts = np.array([pooled[t][1] for t in taus])
    # relative least squares: each tau weighted by sqrt(terms) / sigma^2 (its relative precision)
    w = np.sqrt(np.maximum(counts, 1.0)) / np.maximum(avar, 1e-300)
    A = np.column_stack([taus ** mu for mu in MUS]) * w[:, None]
    scale = np.sqrt(np.sum(A ** 2, axis=0))
    scale[scale == 0] = 1.0
    sol, _ = nnls(A / scale, avar * w)
    coef = {mu: float(c) for mu, c in zip(MUS, sol / scale)}
    return NoiseModel(coef=coef, taus=taus, adev=np.sqrt(avar), tau_max_s=float(taus[-1]))
