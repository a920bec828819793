"""The noise floor of a residual: the std of 100-s means that noise alone would give over a record of
a given length, robust to 1/f (flicker, "bias instability") noise.

Method.  The Allan variance of a residual at short averaging times tau is dominated by the sensor's
noise, not by slow thermal structure.  It is fitted (non-negative least squares on the octave taus
up to ``tau_max``, relative weights by the number of terms) with the IEEE 952 power laws

    sigma^2(tau) = q tau^-2  (quantisation / white phase)  +  w tau^-1 (white rate, ARW)
                 + f tau^0   (flicker, bias instability)    +  k tau^1  (rate random walk)
                 + d tau^2   (slow structure / drift)

A sensor filtered below its output rate (a gyro's internal low-pass, a moving average longer than
the sample period) has correlated samples: its white noise is a first-order Gauss-Markov process of
correlation time T whose Allan variance rises up to about T before it falls as w / tau, a rise the
other terms would read as flicker (on 1-s samples of a 3-s filter the floor came out 2.8x the true
std of 100-s means).  The white term is therefore w / tau (1 - (T / 2 tau)(3 - 4 e^(-tau/T) +
e^(-2 tau/T))), T = 0 unless a T among the sample period times powers of sqrt(2) (up to
``BAND_MAX_S``) lowers the fit's chi-square by more than ``BAND_CHI2_GAIN``.

The last two terms are nuisance terms, NOT part of the floor: at the short taus used, slow structure
left in the residual (a trend or a slow wave grows as tau^2 there, a wander as tau^1) would otherwise
be read as noise; a genuine rate random walk is invisible at those taus anyway (IEEE 952 levels of
navigation and tactical gyros put it orders of magnitude below white and flicker noise at 100 s).  The expected sample variance of M consecutive tau-means of
a power-law noise sigma^2 ~ tau^mu is its Allan variance times Barnes' bias function

    B1(M, mu) = M (1 - M^mu) / (2 (M - 1) (1 - 2^mu))     (mu != 0),   M ln M / (2 (M - 1) ln 2)  (mu = 0)

so for white noise the floor is ADEV(100 s) itself, while flicker noise makes the std of 100-s means
over a long record larger than ADEV(100 s) (B1 grows like ln M).  The floor for a record of M blocks
of 100 s is sqrt(sum_k h_k 100^mu_k B1(M, mu_k)).

Uncertainty: the sample variance of M block means is a quadratic form in correlated Gaussian means.
Its covariance follows from each power law's structure function of tau-means at lag k (the variogram
of the block means, Barnes' B2(k, mu) x 2 AVAR(100 s)):

    D(k) / D(1) = (2 f(1) + 2 f(k) - f(k+1) - f(|k-1|)) / (4 f(1) - f(2)),
    f(t) = t^(mu+2)  (mu != 0),   f(t) = t^2 ln t  (flicker, mu = 0)

With G = -D/2 and the centring matrix A, C = A G A is the covariance of the centred means; then
E[s^2] = tr(C) / (M - 1) (which is Barnes' B1 again) and the Satterthwaite degrees of freedom are
edf = tr(C)^2 / tr(C^2): M - 1 for white noise, far fewer under flicker (about 27 for 288 blocks of
flicker noise, where the former (M - 1) / B1 claimed 70 and made the interval too narrow).  The
reported interval is the central 90 % of noise-only std100 values on that record; ``limit_dph`` is
the one-sided (1 - ``LIMIT_P``) quantile, above which a std100 is not noise alone at the level the
structure tests use.

The verdict's floor (``NoiseModel.floor_over``) is that quadratic form over the blocks actually
judged, at their block numbers (an out-of-range stretch or an outage keeps its length: flicker over
a span, not over as many consecutive blocks), with the training coefficients' error as a second
covariance (``coefficient_spread``); its tail by Pearson's three moments (two, Satterthwaite's, make
it too light when a few slow components dominate), and the fitted noise level's own uncertainty
(the Allan fit's coefficient covariance, ``fit_noise_model``) carried into the interval and the
limit as a predictive (F-like) distribution; a level with no more than ``MIN_LEVEL_EDF`` degrees of
freedom sets no limit (that distribution has no finite mean).
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
PIECE_TAUS = 8.0       # a stretch of L seconds gives Allan variances up to tau = L / PIECE_TAUS
INTERVAL = 0.90
LIMIT_P = 0.01
MIN_LEVEL_EDF = 2.0                  # the fitted noise level must have more degrees of freedom to set a limit
# the white noise's correlation time (a sensor band-limited below its output rate) is searched from the
# sample period up to BAND_MAX_S seconds and kept only when it lowers the Allan fit's chi-square by
# more than BAND_CHI2_GAIN: a filter of one sample period gains 430-540 on 5.5 h of 1-s samples, while
# residuals of white-noise gyros whose fitted effects leave fast jitter gained up to 70 with a
# correlation time of 0.7-2 s and a quantisation term traded against it
BAND_MAX_S = 20.0
BAND_CHI2_GAIN = 100.0


def _structure_ratio(k: np.ndarray, mu: float) -> np.ndarray:
    """D(k) / D(1): the variogram of consecutive tau-means of a power-law noise at lag k (k >= 0)."""
    k = np.asarray(k, dtype=np.float64)
    p = mu + 2.0

    def f(t):
        t = np.asarray(t, dtype=np.float64)
        if abs(mu) < 1e-12:
            return np.where(t > 0, t ** 2 * np.log(np.where(t > 0, t, 1.0)), 0.0)
        return np.where(t > 0, np.abs(t) ** p, 0.0)

    den = 4.0 * f(1.0) - f(2.0)
    return np.where(k == 0, 0.0, (2.0 * f(1.0) + 2.0 * f(k) - f(k + 1.0) - f(np.abs(k - 1.0))) / den)


def block_means_edf(m: int, allan_parts: dict[float, float]) -> float:
    """Satterthwaite degrees of freedom of the sample variance of ``m`` consecutive block means of a
    sum of power-law noises (``allan_parts``: mu -> its Allan variance at the block length).

    With G the Toeplitz matrix g(|i-j|) = -D(|i-j|)/2 and P = 11'/m, C = (I-P) G (I-P): tr(C) =
    m g(0) - s/m and tr(C^2) = tr(G^2) - 2 |G1|^2 / m + (s/m)^2 with s = 1'G1 -- all O(m) from the
    lag sums of a Toeplitz matrix, no m x m matrix."""
    m = int(max(m, 2))
    g = np.zeros(m)
    for mu, avar in allan_parts.items():
        if avar > 0:
            g -= avar * _structure_ratio(np.arange(m), mu)    # -D/2 per lag, D(1) = 2 AVAR
    cg = np.cumsum(g)
    i = np.arange(m)
    rows = cg[i] + cg[m - 1 - i] - g[0]                       # G1: row sums of the Toeplitz matrix
    s = float(rows.sum())
    counts = np.concatenate([[m], 2.0 * (m - np.arange(1, m))])
    tr = m * g[0] - s / m
    tr2 = float(np.sum(counts * g ** 2)) - 2.0 * float(rows @ rows) / m + (s / m) ** 2
    return tr * tr / tr2 if tr2 > 0 else float(m - 1)


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
    cov: np.ndarray | None = None      # covariance of the floor terms' h_mu (``MUS`` order) given the nuisance terms
    # correlation time (s) of the white rate noise: a sensor filtered below its output rate (``band_limited``)
    white_corr_s: float = 0.0

    def term(self, mu: float, tau: float) -> float:
        """One power law's Allan variance at ``tau``: h_mu tau^mu, the white term band-limited by
        ``white_corr_s``."""
        v = self.coef.get(mu, 0.0) * tau ** mu
        return v * band_limited(tau, self.white_corr_s) if mu == -1.0 else v

    def allan_var(self, tau: float, mus=NOISE_MUS) -> float:
        return float(sum(self.term(mu, tau) for mu in mus))

    def floor(self, record_s: float, block_s: float = BLOCK_S, mus: tuple[float, ...] = NOISE_MUS,
              spread: "CoefficientSpread | None" = None) -> dict[str, Any]:
        """Expected std of ``block_s`` means over ``record_s`` seconds, with its interval (``mus``: the
        noise terms counted; the white-only floor, ``mus=WHITE_MUS``, is a lower bound).  With
        ``spread`` (a model fitted on another run and judged on this one), the variance the training
        noise put into the fitted coefficients is added, the degrees of freedom combined
        (Satterthwaite)."""
        m = max(2.0, np.floor(record_s / block_s))
        parts = {mu: self.term(mu, block_s) * barnes_b1(m, mu) for mu in mus}
        var = float(sum(parts.values()))
        if var <= 0:
            return {"noise_floor_dph": float("nan"), "interval_dph": [float("nan"), float("nan")], "edf": 0.0,
                    "blocks": int(m)}
        allan_100 = self.allan_var(block_s, mus)
        edf = max(1.0, block_means_edf(int(m), {mu: self.term(mu, block_s) for mu in mus}))
        noise_var = var
        if spread is not None and spread.variance > 0:
            var = noise_var + spread.variance
            edf = var ** 2 / (noise_var ** 2 / edf + spread.variance ** 2 / spread.edf)
        lo = np.sqrt(var * chi2.ppf((1 - INTERVAL) / 2, edf) / edf)
        hi = np.sqrt(var * chi2.ppf((1 + INTERVAL) / 2, edf) / edf)
        limit = np.sqrt(var * chi2.ppf(1 - LIMIT_P, edf) / edf)
        return {"noise_floor_dph": float(np.sqrt(var)), "interval_dph": [float(lo), float(hi)],
                "limit_dph": float(limit), "edf": float(edf), "noise_only_dph": float(np.sqrt(noise_var)),
                "coefficient_spread_dph": float(np.sqrt(spread.variance)) if spread is not None else 0.0,
                "blocks": int(m), "adev100_dph": float(np.sqrt(max(allan_100, 0.0))),
                "flicker_share": float(parts.get(0.0, 0.0) / var)}

    def floor_over(self, block_index: np.ndarray, spread: "CoefficientSpread | None" = None,
                   mus: tuple[float, ...] = NOISE_MUS, block_s: float = BLOCK_S) -> dict[str, Any]:
        """``floor`` for the blocks actually judged: ``block_index`` numbers them from the run's start
        (a stretch out of range or a logger outage keeps its lag, so flicker and random walk over the
        span they cover count, not over as many consecutive blocks).  The judged std of block means is
        the root of a Gaussian quadratic form: its covariance K = A (G + W) A / (M - 1) (G the noise
        terms' covariance of the block means at their lags, W = ``spread.block_cov`` the training
        coefficients' error, A the centring).  Its mean is tr K; its quantiles come from tr K, tr K^2 and
        tr K^3 by Pearson's three-moment chi-square approximation (Satterthwaite's two moments make the
        upper tail too light when a few slow components dominate), widened by the uncertainty of the
        fitted noise level (``floor_edf``)."""
        idx = np.rint(np.asarray(block_index, dtype=np.float64)).astype(np.int64)
        m = len(idx)
        if m < 2:
            return {"noise_floor_dph": float("nan"), "interval_dph": [float("nan"), float("nan")],
                    "limit_dph": float("nan"), "edf": 0.0, "blocks": int(m)}
        # each noise term's covariance of the centred means once: their sum is the noise's, their traces
        # the terms' shares
        per_mu = {mu: centred(block_covariance(self, idx, block_s, (mu,))) for mu in mus}
        noise = sum(per_mu.values())
        w = spread.block_cov if spread is not None and spread.block_cov is not None else None
        if w is not None and w.shape != (m, m):
            w = None
        k = noise + (centred(w) if w is not None else 0.0)
        k = 0.5 * (k + k.T) / (m - 1)
        c1, c2, c3 = float(np.trace(k)), float(np.sum(k * k)), float(np.sum((k @ k) * k))
        var, noise_var = c1, float(np.trace(noise)) / (m - 1)
        if w is None and spread is not None and spread.variance > 0:
            var += spread.variance             # no block covariance: its expected variance only
        if not var > 0 or not c1 > 0:
            return {"noise_floor_dph": float("nan"), "interval_dph": [float("nan"), float("nan")],
                    "limit_dph": float("nan"), "edf": 0.0, "blocks": int(m)}
        parts = {mu: float(np.trace(c)) / (m - 1) for mu, c in per_mu.items()}
        model_edf = self.floor_edf(parts)
        r = var / c1                           # the fallback above scales the form as a whole
        lo, hi, limit = quadratic_form_quantiles((var, c2 * r * r, c3 * r ** 3),
                                                 ((1 - INTERVAL) / 2, (1 + INTERVAL) / 2, 1 - LIMIT_P), model_edf)
        # a level with <= 2 degrees of freedom (the short taus cannot separate the noise terms, e.g. a
        # slow structure dominating from a few sample periods on): a new std judged against it has a
        # predictive distribution without a finite mean, and its "limit" would pass any std as noise.
        # No limit then; the verdict has the floor itself (1.2x) to go by
        limit = limit if model_edf > MIN_LEVEL_EDF else float("nan")
        return {"noise_floor_dph": float(np.sqrt(var)), "interval_dph": [float(np.sqrt(lo)), float(np.sqrt(hi))],
                "limit_dph": float(np.sqrt(limit)), "edf": float(c1 * c1 / c2) if c2 > 0 else float(m - 1),
                "noise_only_dph": float(np.sqrt(noise_var)),
                "coefficient_spread_dph": float(np.sqrt(max(var - noise_var, 0.0))),
                "blocks": int(m), "span_blocks": int(idx.max() - idx.min() + 1),
                "adev100_dph": float(np.sqrt(max(self.allan_var(block_s, mus), 0.0))),
                "flicker_share": float(parts.get(0.0, 0.0) / var),
                "random_walk_share": float(parts.get(1.0, 0.0) / var),
                "noise_model_edf": float(model_edf)}

    def floor_edf(self, parts: dict[float, float]) -> float:
        """Degrees of freedom of the fitted noise variance sum_mu parts[mu] (each part proportional to
        its h_mu): 2 v^2 / Var(v) from the fit's coefficient covariance; inf without one."""
        if self.cov is None:
            return float("inf")
        g = np.array([parts.get(mu, 0.0) / self.coef[mu] if self.coef.get(mu, 0.0) > 0 else 0.0 for mu in MUS])
        v = float(sum(parts.values()))
        var_v = float(g @ self.cov @ g)
        return 2.0 * v * v / var_v if var_v > 0 and v > 0 else float("inf")

    def summary(self) -> dict[str, Any]:
        h = self.coef
        return {"white_dph_at_1s": float(np.sqrt(max(h.get(-1.0, 0.0), 0.0))),
                "flicker_adev_dph": float(np.sqrt(max(h.get(0.0, 0.0), 0.0))),
                "quantisation_dph_s": float(np.sqrt(max(h.get(-2.0, 0.0), 0.0))),
                "rate_random_walk_dph_per_rt_s": float(np.sqrt(max(h.get(1.0, 0.0), 0.0))),
                "structure_term_dph_per_s": float(np.sqrt(max(h.get(2.0, 0.0), 0.0))),
                "white_correlation_s": float(self.white_corr_s),
                "tau_max_s": float(self.tau_max_s)}


@dataclass
class CoefficientSpread:
    """What the training noise adds to a validation std of block means through the fitted
    coefficients: a model of the true form, fitted on a noisy run, still errs by X_val (b - beta).
    ``variance`` is the expected contribution to the sample variance of the validation block means,
    ``edf`` its Satterthwaite degrees of freedom (at most the number of coefficients); ``block_cov``
    the covariance V Sigma V' of that error over the validation blocks judged (in their order)."""

    variance: float
    edf: float
    block_cov: np.ndarray | None = None


def centred(g: np.ndarray) -> np.ndarray:
    """A g A with A = I - 11'/m (the covariance of centred values), in O(m^2)."""
    g = np.asarray(g, dtype=np.float64)
    return g - g.mean(axis=0, keepdims=True) - g.mean(axis=1, keepdims=True) + g.mean()


def quadratic_form_quantiles(cumulants: tuple[float, float, float], probs,
                             scale_edf: float = float("inf")) -> list[float]:
    """Quantiles of sum_i lam_i chi2_1 (lam >= 0, the eigenvalues of a covariance K; ``cumulants`` =
    (c1, c2, c3), c_j = sum lam^j = tr K^j) by Pearson's three-moment approximation: a shifted, scaled
    chi-square a + b X, X ~ chi2_l, with the form's mean c1, variance 2 c2 and skewness
    (l = c2^3 / c3^2: it follows the largest eigenvalues).  With ``scale_edf`` = nu
    finite, the lam are an estimate whose scale is itself uncertain, v_hat / v ~ chi2_nu / nu: the
    quantiles are those of (a + b X) nu / Y, Y ~ chi2_nu independent (the predictive distribution of
    a new sample variance judged against an estimated one, an F distribution when a = 0)."""
    from scipy.optimize import brentq

    c1, c2, c3 = (float(c) for c in cumulants)
    if not (c2 > 0 and c3 > 0):
        return [c1 for _ in probs]
    df = c2 ** 3 / c3 ** 2
    b = np.sqrt(c2 / df)
    a = c1 - b * df
    if not np.isfinite(scale_edf) or scale_edf <= 0:
        return [max(0.0, a + b * chi2.ppf(p, df)) for p in probs]
    # Y on a grid of its own quantiles (midpoints): P(Q > q) = E_Y[P(X > (q Y / nu - a) / b)]
    y = chi2.ppf((np.arange(400) + 0.5) / 400.0, scale_edf) / scale_edf

    def sf(q: float) -> float:
        return float(np.mean(chi2.sf(np.maximum((q * y - a) / b, 0.0), df)))

    out = []
    for p in probs:
        if sf(0.0) <= 1.0 - p:
            out.append(0.0)
            continue
        hi = max(a + b * chi2.ppf(p, df), c1)
        while sf(hi) > 1.0 - p:
            hi *= 2.0
        out.append(float(brentq(lambda q: sf(q) - (1.0 - p), 0.0, hi, xtol=1e-12 * hi)))
    return out


def coefficient_spread(model: NoiseModel, train_blocks: np.ndarray, block_index: np.ndarray,
                       validate_blocks: np.ndarray, block_s: float = BLOCK_S,
                       mus: tuple[float, ...] = NOISE_MUS) -> CoefficientSpread:
    """Under the fitted noise, the training block means' covariance is G (g(|i-j|) = -D(|i-j|)/2 from
    each power law's structure function, up to a constant the intercept absorbs), so the least-squares
    coefficients b = B y (B = pinv(X)) spread with Sigma = B G B'.  With S the covariance of the
    centred validation design's block means, E[extra sample variance] = tr(Sigma S) and edf =
    tr(Sigma S)^2 / tr((Sigma S)^2).  ``train_blocks``: (n, k) block means of the design on TRAIN
    (intercept included), ``block_index``: each block's number from the run's start (gaps keep their
    lag), ``validate_blocks``: the same design's block means on the validation part judged."""
    X = np.asarray(train_blocks, dtype=np.float64)
    idx = np.asarray(block_index, dtype=np.float64)
    ok = np.all(np.isfinite(X), axis=1)
    X, idx = X[ok], idx[ok]
    V = np.asarray(validate_blocks, dtype=np.float64)
    V = V[np.all(np.isfinite(V), axis=1)]
    if len(X) <= X.shape[1] or len(V) < 2:
        return CoefficientSpread(0.0, 1.0)
    g = block_covariance(model, idx, block_s, mus)
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    scale[~(scale > 0)] = 1.0
    B = np.linalg.pinv(X / scale) / scale[:, None]
    sigma = B @ g @ B.T
    Vc = V - V.mean(axis=0)
    P = sigma @ (Vc.T @ Vc / (len(Vc) - 1))
    e = float(np.trace(P))
    e2 = float(np.trace(P @ P))
    if not (e > 0 and e2 > 0):
        return CoefficientSpread(0.0, 1.0)
    return CoefficientSpread(e, max(1.0, e * e / e2), Vc @ sigma @ Vc.T)


def block_covariance(model: NoiseModel, block_index: np.ndarray, block_s: float = BLOCK_S,
                     mus: tuple[float, ...] = NOISE_MUS) -> np.ndarray:
    """The generalised covariance G of block means under the fitted noise terms (``NOISE_MUS``):
    g(|i-j|) = -D(|i-j|) / 2 from each power law's structure function, D(1) = 2 AVAR(block_s), at
    the blocks' numbers ``block_index`` (an outage keeps its lag).  Defined up to a constant: only
    contrasts (a design with an intercept) have a variance under it; flicker has no finite one."""
    idx = np.rint(np.asarray(block_index, dtype=np.float64)).astype(np.int64)
    lags = np.abs(idx[:, None] - idx[None, :])
    per_lag = np.zeros(int(lags.max()) + 1 if lags.size else 0)
    for mu in mus:
        avar = model.term(mu, block_s)
        if avar > 0:
            per_lag -= avar * _structure_ratio(np.arange(len(per_lag)), mu)
    return per_lag[lags]


def realised_scale(g: np.ndarray, means: np.ndarray) -> float:
    """The factor (at most 1) that brings the generalised covariance ``g`` of block means down to the
    sample variance the block means ``means`` themselves realise: that variance over its expectation
    under ``g``, tr(A g A) / (M - 1) with A the centring matrix, when the expectation is the larger, else
    1.  A noise model fitted to a residual at short taus and carried over a long span (a random-walk
    term read from taus up to ~1000 s) can claim more variance over the span than the residual holds;
    the realised variance bounds what its noise can put there."""
    m = len(means)
    if m < 2:
        return 1.0
    expected = float(np.trace(centred(g))) / (m - 1)
    realised = float(np.var(means, ddof=1))
    return realised / expected if expected > realised > 0 else 1.0


def gls_whitener(g: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor L of a proper covariance with the contrasts of the generalised covariance
    ``g`` (g + c 11', c = 2 max|g|: nonnegative, convex and decreasing in the lag, hence positive
    definite by Polya's criterion).  A design with an intercept gets the same generalised least
    squares fit and residual sum of squares for any such c (the added part lies in the intercept's
    direction), so solving with L whitens the block means under the noise model."""
    from scipy.linalg import cholesky

    from bench.signal.lstsq import blas_threads

    n = len(g)
    c = 2.0 * float(np.max(np.abs(g))) if n else 0.0
    if not c > 0:
        return np.eye(n)
    with blas_threads():
        return cholesky(g + c, lower=True)


def gls_f_test(L: np.ndarray, X0: np.ndarray, X1: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """F test that the columns X1 adds to X0 are zero, by generalised least squares with the noise
    model's covariance of block means (``gls_whitener``: L; an intercept is added to both designs),
    its scale estimated from the residual (so structure left by other missing terms makes the test
    conservative, not liberal).  Autocorrelation of any shape the noise model describes (white,
    flicker) is accounted for, where a lag-1 or Newey-West correction under-prices slow regressors
    against 1/f noise.  Returns (F, p)."""
    from scipy.linalg import solve_triangular
    from scipy.stats import f as f_dist

    one = np.ones((len(y), 1))
    A = solve_triangular(L, np.column_stack([y, one, X0, X1[:, X0.shape[1]:]]), lower=True, check_finite=False)
    yw, k0 = A[:, 0], 1 + X0.shape[1]

    def ssr_rank(B: np.ndarray) -> tuple[float, int]:
        sc = np.sqrt(np.mean(B ** 2, axis=0))
        sc[~(sc > 0)] = 1.0
        u, sv, _ = np.linalg.svd(B / sc, full_matrices=False)
        q = u[:, sv > (sv[0] if len(sv) else 0.0) * 1e-10]
        r = yw - q @ (q.T @ yw)
        return float(r @ r), q.shape[1]

    s0, r0 = ssr_rank(A[:, 1:1 + k0])
    s1, r1 = ssr_rank(A[:, 1:])
    q, dof = r1 - r0, len(yw) - r1
    if q <= 0 or dof <= 0 or s1 <= 0:
        return 0.0, 1.0
    stat = max(s0 - s1, 0.0) / q / (s1 / dof)
    return float(stat), float(f_dist.sf(stat, q, dof))


def _oadev_octave(x: np.ndarray, dt: float, tau_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance (``bench.signal.allan_deviation``) at octave multiples of dt up to
    tau_max: (taus, variances, number of terms)."""
    from bench.signal import allan_deviation

    taus = dt * 2.0 ** np.arange(0, int(np.floor(np.log2(max(tau_max / dt, 1.0)))) + 1)
    res = allan_deviation(x, 1.0 / dt, taus=taus)
    return res.taus_s, res.adev ** 2, res.n


def contiguous_pieces(x: np.ndarray, dt: float, time_s: np.ndarray | None = None) -> list[np.ndarray]:
    """The stretches of ``x`` with every sample finite and (with ``time_s``) no step longer than 1.5
    sample periods: an Allan difference across a missing stretch or a logger outage is not a
    difference over tau, so each stretch is its own series."""
    x = np.asarray(x, dtype=np.float64)
    cut = ~np.isfinite(x)
    breaks = np.zeros(len(x), dtype=bool)
    if time_s is not None and len(x) > 1:
        breaks[1:] = np.diff(np.asarray(time_s, dtype=np.float64)) > 1.5 * dt
    label = np.cumsum(breaks | np.concatenate([[False], cut[:-1] != cut[1:]]))
    out = []
    for lab in np.unique(label[~cut]):
        piece = x[(label == lab) & ~cut]
        out.append(piece)
    return out


def _block_allan(x: np.ndarray, dt: float, time_s: np.ndarray | None, tau_max_s: float, reach_s: float):
    """Allan variances at taus the contiguous stretches cannot reach, across their breaks: the
    overlapping Allan variance of ``BLOCK_S`` means numbered by time (a block counts when it holds at
    least 90 % of its samples; a tau-window counts when all its blocks do, so a missing row or an
    outage removes the differences that span it, not the lags), at tau = BLOCK_S 2^j in
    (``reach_s``, ``tau_max_s``].  Yields (tau, Allan variance, number of differences, edf per
    ``MUS`` entry), the edf of the blocks' span scaled by the share of differences present."""
    x = np.asarray(x, dtype=np.float64)
    t = np.arange(len(x)) * dt if time_s is None else np.asarray(time_s, dtype=np.float64)
    ok = np.isfinite(x) & np.isfinite(t)
    if ok.sum() < 2 or BLOCK_S <= dt:
        return
    b = np.floor((t[ok] - t[ok][0]) / BLOCK_S).astype(np.int64)
    cnt = np.bincount(b)
    sums = np.bincount(b, weights=x[ok])
    full = cnt >= 0.9 * BLOCK_S / dt
    means = np.where(full, sums / np.maximum(cnt, 1), 0.0)
    nb = len(cnt)
    m = 1
    while m * BLOCK_S <= tau_max_s and 4 * m <= nb:
        tau = m * BLOCK_S
        if tau > reach_s:
            cs = np.concatenate([[0.0], np.cumsum(means)])
            cf = np.concatenate([[0], np.cumsum(full.astype(np.int64))])
            starts = np.arange(nb - 2 * m + 1)
            good = (cf[starts + 2 * m] - cf[starts]) == 2 * m
            if good.sum() >= 2:
                a = (cs[starts + m] - cs[starts]) / m
                c = (cs[starts + 2 * m] - cs[starts + m]) / m
                d = (c - a)[good]
                share = good.sum() / len(starts)
                edf = np.array([allan_edf(nb, m, mu) for mu in MUS]) * share
                yield tau, 0.5 * float(np.mean(d * d)), float(good.sum()), edf
        m *= 2


def allan_edf(n: np.ndarray, m: float, mu: float) -> np.ndarray:
    """Equivalent degrees of freedom of an overlapping Allan variance at tau = m samples from stretches
    of ``n`` samples, per noise type (the simple approximations of NIST SP 1065, Table 5, after Howe,
    Allan and Barnes): white rate (also used for quantisation), flicker rate, random-walk rate (also
    used for the drift term)."""
    n = np.asarray(n, dtype=np.float64)
    m = float(m)
    if mu <= -1.0:
        e = (3.0 * (n - 1) / (2.0 * m) - 2.0 * (n - 2) / n) * 4.0 * m * m / (4.0 * m * m + 5.0)
    elif mu == 0.0:
        e = 2.0 * (n - 2) / (2.3 * n - 4.9) if m == 1 else 5.0 * n * n / (4.0 * m * (n + 3.0 * m))
    else:
        e = (n - 2) / m * ((n - 1) ** 2 - 3.0 * m * (n - 1) + 4.0 * m * m) / np.maximum((n - 3) ** 2, 1.0)
    return np.maximum(e, 1.0)


def fit_noise_model(residuals: list[tuple], tau_max_s: float = TAU_MAX_S) -> NoiseModel:
    """Fit the power laws to the pooled Allan variance of one or more residual series, each given as
    (values, sample period) or (values, sample period, time_s).  Each series is cut into its
    contiguous finite stretches (``contiguous_pieces``); stretches are pooled per tau, weighted by
    their number of terms.

    Weights: each tau's Allan variance is weighted by its precision, edf / (2 sigma^4), with sigma^2
    the fitted model's value (not the observed one: weighting by the inverse of the observed value
    favours the taus that came out low and biases the flicker level down) and edf summed over the
    stretches (``allan_edf``, mixed by each noise type's share of the model at that tau); a few
    re-weighted passes.  The covariance of the fitted coefficients (non-negative ones held at zero)
    is kept (the floor terms' given the nuisance terms): the floor carries it into its limit."""
    pooled: dict[float, list] = {}

    def add(tau: float, v: float, k: float, edf: np.ndarray) -> None:
        acc = pooled.setdefault(round(float(tau), 6), [0.0, 0.0, np.zeros(len(MUS))])
        acc[0] += v * k
        acc[1] += k
        acc[2] += edf

    for item in residuals:
        x, dt = item[0], item[1]
        t = item[2] if len(item) > 2 else None
        reach = 0.0
        for piece in contiguous_pieces(x, dt, t):
            if len(piece) < 16:
                continue
            tmax = min(tau_max_s, len(piece) * dt / PIECE_TAUS)
            taus, avar, n = _oadev_octave(piece, dt, tmax)
            for tau, v, k in zip(taus, avar, n):
                add(tau, v, k, np.array([allan_edf(len(piece), max(1.0, round(tau / dt)), mu) for mu in MUS]))
                reach = max(reach, float(tau))
        for tau, v, k, edf in _block_allan(x, dt, t, tau_max_s, reach):
            add(tau, v, k, edf)
    if not pooled:
        raise ValueError("noise floor: the residual is too short for an Allan deviation")
    taus = np.array(sorted(pooled))
    avar = np.array([pooled[t][0] / pooled[t][1] for t in taus])
    edf_by_mu = np.maximum(np.array([pooled[t][2] for t in taus]), 1.0)
    # the white term's correlation time: none, or the one (the sample period times a power of sqrt 2) that fits the
    # short taus better by more than ``BAND_CHI2_GAIN`` (a sensor filtered below its output rate has an
    # Allan variance that rises to its bandwidth before it falls as white noise; read as flicker, that
    # rise multiplied the floor)
    fits = [(0.0, *_fit_power_laws(taus, avar, edf_by_mu, 0.0))]
    dt_min = min(float(item[1]) for item in residuals)
    for corr in dt_min * 2.0 ** (np.arange(0, 24) / 2.0):
        if corr > min(BAND_MAX_S, taus[-1] / 8.0):
            break
        fits.append((float(corr), *_fit_power_laws(taus, avar, edf_by_mu, float(corr))))
    best = min(fits, key=lambda f: f[3])
    corr, sol, w, _ = best if best[3] < fits[0][3] - BAND_CHI2_GAIN else fits[0]
    A0 = _power_law_columns(taus, corr)
    # the floor terms' covariance given the nuisance terms (tau^1, tau^2: structure, never part of the
    # floor) at their fitted values: a slow excess that the nuisance and flicker terms could share is
    # structure, not uncertainty of the noise level (their joint covariance made the level unknowable,
    # edf << 1, on a residual with a strong slow component, and any std then passed as noise)
    active = sol > 0
    floor_active = active & np.isin(np.array(MUS), NOISE_MUS)
    cov = np.zeros((len(MUS), len(MUS)))
    if floor_active.any():
        Af = (A0 * w[:, None])[:, floor_active]
        cov[np.ix_(floor_active, floor_active)] = np.linalg.pinv(Af.T @ Af)
    coef = {mu: float(c) for mu, c in zip(MUS, sol)}
    return NoiseModel(coef=coef, taus=taus, adev=np.sqrt(avar), tau_max_s=float(taus[-1]), cov=cov,
                      white_corr_s=corr)


def band_limited(tau, corr_s: float):
    """Allan variance of white noise passed through a first-order filter of time constant ``corr_s``
    (a first-order Gauss-Markov process), relative to unfiltered white noise of the same level at long
    taus: 1 - (T / 2 tau) (3 - 4 e^(-tau/T) + e^(-2 tau/T)).  Below T it is about (tau / T)^2 / 3, so
    the Allan variance rises as w tau / (3 T^2) there (the filtered samples are correlated); above T
    it tends to 1; 1 for T = 0."""
    tau = np.asarray(tau, dtype=np.float64)
    if corr_s <= 0:
        return np.ones_like(tau) if tau.ndim else 1.0
    u = tau / corr_s
    out = 1.0 - (3.0 - 4.0 * np.exp(-u) + np.exp(-2.0 * u)) / (2.0 * u)
    return out if tau.ndim else float(out)


def _power_law_columns(taus: np.ndarray, corr_s: float) -> np.ndarray:
    cols = np.column_stack([taus ** mu for mu in MUS])
    cols[:, MUS.index(-1.0)] *= band_limited(taus, corr_s)
    return cols


def _fit_power_laws(taus: np.ndarray, avar: np.ndarray, edf_by_mu: np.ndarray, corr_s: float):
    """Non-negative weighted least squares of the power laws (white term band-limited by ``corr_s``)
    to the Allan variances: each tau weighted by its precision edf / (2 sigma^4), sigma^2 the fitted
    model's value (not the observed one: weighting by the inverse of the observed value favours the
    taus that came out low and biases the flicker level down), edf mixed by each noise type's share
    of the model at that tau; a few re-weighted passes.  Returns the coefficients, the final weights
    and the weighted sum of squares (a chi-square under those precisions)."""
    A0 = _power_law_columns(taus, corr_s)
    floor_v = np.maximum(avar, 1e-300)
    model_v = floor_v.copy()
    sol = np.zeros(len(MUS))
    for _ in range(4):
        share = np.where(A0 * sol > 0, A0 * sol, 0.0)
        share = share / share.sum(axis=1, keepdims=True) if np.any(sol > 0) else np.full_like(A0, 1.0 / len(MUS))
        edf = 1.0 / np.sum(share / edf_by_mu, axis=1)
        w = np.sqrt(edf / 2.0) / np.maximum(model_v, 1e-300)
        A = A0 * w[:, None]
        scale = np.sqrt(np.sum(A ** 2, axis=0))
        scale[scale == 0] = 1.0
        sol_s, _ = nnls(A / scale, avar * w)
        sol = sol_s / scale
        model_v = np.maximum(A0 @ sol, 1e-3 * floor_v)
    chi2_w = float(np.sum(((avar - A0 @ sol) * w) ** 2))
    return sol, w, chi2_w
