"""Least squares: the one solver.

``lstsq(x, y)``: ordinary (optionally weighted) least squares for large designs (10^6 x 40).  Columns
are equilibrated (divided by their 2-norm; calibration-notes lesson 2/10: ill-conditioning, not the
optimiser, is the usual problem) and the 2-norm condition number of the equilibrated design is
reported as ``cond``.  When cond <= 1e6 the fast path solves the equilibrated normal equations by
eigen-decomposition and applies one step of iterative refinement on the residual (corrected
semi-normal equations; one BLAS pass per step, ~10 significant digits left).  Worse-conditioned
designs go through a chunked Householder QR of [X/s, y] (TSQR: R factors of row blocks stacked and
reduced again) and an SVD of R with relative cut-off ``rcond`` (rank reported).  BLAS runs with
``BLAS_THREADS`` (default 1, via threadpoolctl: ``blas_threads()``) threads during the solve.  Rows with
any non-finite value in X, y or the weights are left out and get a NaN residual.  Units: those of the
design.
"""
from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass

import numpy as np


@dataclass
class LinearFit:
    coef: np.ndarray            # in the units of the (unscaled) design
    names: list[str]
    residual: np.ndarray        # y - X @ coef, NaN for rows left out
    used: np.ndarray            # bool, rows used in the fit
    n: int
    k: int
    rank: int
    cond: float                 # condition number of the column-equilibrated design
    rss: float
    rms: float
    r2: float
    bic: float

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, (float(c) for c in self.coef)))

    def stats(self) -> dict[str, float | int]:
        return {"n": self.n, "k": self.k, "rank": self.rank, "cond": self.cond, "rss": self.rss,
                "rms_dph": self.rms, "r2": self.r2, "bic": self.bic}


def bic(rss: float, n: int, k: int) -> float:
    """Gaussian BIC up to a constant: n ln(rss/n) + k ln n."""
    if n <= 0 or rss <= 0:
        return float("nan")
    return float(n * np.log(rss / n) + k * np.log(n))


def _chunks(x: np.ndarray, y: np.ndarray, used: np.ndarray, sw: np.ndarray | None, chunk_rows: int):
    """Yield (x rows, y rows) of the used rows, weighted, one row block at a time (no full copy)."""
    n_all = x.shape[0]
    if sw is None and used.all():
        yield x, y                  # whole matrix: one BLAS call, no copy
        return
    for start in range(0, n_all, chunk_rows):
        stop = min(n_all, start + chunk_rows)
        m = used[start:stop]
        if not m.any():
            continue
        xs = np.array(x[start:stop], order="F")       # contiguous copy so that matmul goes to BLAS
        ys = np.array(y[start:stop])
        if not m.all():                               # unused rows -> zero rows (contribute nothing)
            xs[~m] = 0.0
            ys[~m] = 0.0
        if sw is not None:
            w = sw[start:stop]
            xs *= w[:, None]
            ys *= w
        yield xs, ys


def lstsq(x: np.ndarray, y: np.ndarray, *, names: list[str] | None = None, weights: np.ndarray | None = None,
          rcond: float = 1e-12, chunk_rows: int = 131072) -> LinearFit:
    """Least squares of y on the columns of x (add your own intercept column).

    Rows where y, a weight or any x value is not finite are left out (NaN residual)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 1 or x.shape[0] != y.shape[0]:
        raise ValueError(f"lstsq: shapes x{x.shape} y{y.shape} do not match")
    n_all, k = x.shape
    names = list(names) if names is not None else [f"c{j}" for j in range(k)]
    used = np.isfinite(y)
    for j in range(k):
        used &= np.isfinite(x[:, j])
    sw = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        used &= np.isfinite(w) & (w > 0)
        sw = np.sqrt(np.where(used, w, 0.0))
    n = int(used.sum())
    if n < k:
        raise ValueError(f"lstsq: {n} usable rows for {k} coefficients")
    with blas_threads():
        coef, rank, cond = _solve(x, y, used, sw, rcond, chunk_rows)
        resid = y - x @ coef
    resid[~used] = np.nan
    ru, yu = resid[used], y[used]
    if sw is not None:
        wu = sw[used] ** 2
        rss = float(np.sum(wu * ru ** 2))
        ybar = np.sum(wu * yu) / np.sum(wu)
        tss = float(np.sum(wu * (yu - ybar) ** 2))
        rms = float(np.sqrt(rss / np.sum(wu)))
    else:
        rss = float(np.dot(ru, ru))
        tss = float(np.sum((yu - yu.mean()) ** 2))
        rms = float(np.sqrt(rss / n))
    r2 = 1.0 - rss / tss if tss > 0 else float("nan")
    return LinearFit(coef=coef, names=names, residual=resid, used=used, n=n, k=k, rank=rank,
                     cond=cond, rss=rss, rms=rms, r2=float(r2), bic=bic(rss, n, k))


_SEMI_NORMAL_MAX_COND = 1e6

# The tall-skinny products here are memory-bound: one BLAS thread is nearly as fast as several on an
# idle machine and avoids the spin-wait collapse of multi-threaded OpenBLAS on a loaded one (measured
# on the 2-core bench PC: 37 x 10^6 solve 2.6 s with default threads vs 0.3 s with one).
# None = leave the BLAS library's own thread count.
BLAS_THREADS: int | None = 1


def blas_threads():
    """Context manager: BLAS limited to ``BLAS_THREADS`` threads inside (the one thread policy of the
    numerical code: this solver, the close-the-loop search, the noise model's Cholesky factor)."""
    if BLAS_THREADS is None:
        return contextlib.nullcontext()
    return _blas_controller().limit(limits=BLAS_THREADS, user_api="blas")


@functools.cache
def _blas_controller():
    """The process's BLAS libraries as threadpoolctl finds them, looked up once (measured: 2.1 ms a
    look-up, against 0.02 ms a limit; close-the-loop enters this a thousand times on one corpus seed).
    numpy's and scipy's BLAS are both loaded first, so both are limited."""
    import scipy.linalg  # noqa: F401  (scipy's own BLAS: loaded before the look-up)
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _solve(x: np.ndarray, y: np.ndarray, used: np.ndarray, sw: np.ndarray | None, rcond: float,
           chunk_rows: int) -> tuple[np.ndarray, int, float]:
    """Solve min |W^1/2 (x b - y)| over the used rows.  Returns (b, rank, cond of the equilibrated x).

    Fast path (cond <= 1e6): corrected semi-normal equations on the equilibrated Gram matrix
    (eigen-decomposition with cut-off, then one step of iterative refinement on the residual), which
    keeps ~10 significant digits.  Otherwise a chunked Householder QR (TSQR) of [x/s, y]."""
    k = x.shape[1]
    g = np.zeros((k, k))
    xty = np.zeros(k)
    for xs, ys in _chunks(x, y, used, sw, chunk_rows):
        g += xs.T @ xs
        xty += xs.T @ ys
    d = np.sqrt(np.diag(g)).copy()
    d[d == 0] = 1.0
    gs = g / np.outer(d, d)
    evals, evecs = np.linalg.eigh(gs)
    top = evals[-1]
    cond = float(np.sqrt(top / evals[0])) if evals[0] > 0 else float("inf")
    if cond <= _SEMI_NORMAL_MAX_COND:
        keep = evals > top * rcond ** 2
        inv = evecs[:, keep] @ np.diag(1.0 / evals[keep]) @ evecs[:, keep].T
        coef = (inv @ (xty / d)) / d
        resid = np.where(used, y, 0.0)
        resid[used] -= (x @ coef)[used]
        xtr = np.zeros(k)
        for xs, rs_ in _chunks(x, resid, used, sw, chunk_rows):
            xtr += xs.T @ rs_
        coef = coef + (inv @ (xtr / d)) / d
        return coef, int(keep.sum()), cond
    rs = []
    for xs, ys in _chunks(x, y, used, sw, chunk_rows):
        block = np.empty((xs.shape[0], k + 1), order="F")
        block[:, :k] = xs
        block[:, :k] /= d
        block[:, k] = ys
        rs.append(np.linalg.qr(block, mode="r"))          # (min(m, k+1), k+1)
    r = rs[0] if len(rs) == 1 else np.linalg.qr(np.vstack(rs), mode="r")
    if r.shape[0] < k + 1:
        r = np.vstack([r, np.zeros((k + 1 - r.shape[0], k + 1))])
    u, s, vt = np.linalg.svd(r[:k, :k])
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    keep = s > rcond * s[0]
    coef = (vt[keep].T @ ((u[:, keep].T @ r[:k, k]) / s[keep])) / d
    return coef, int(keep.sum()), cond
