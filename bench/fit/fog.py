"""FOG start-up models of seed 004 (BAI et al., FOG start-up temperature modelling).

Two models of the bias ``Y`` (deg/h) over the gyro temperature ``T`` (deg C) and its rate ``dT``
(dT/dt in deg C/min), both computed on 100-s smoothed data as in the paper (section 3: "百秒平滑",
then the rate by differencing the smoothed temperature):

* ``fog_stepwise`` -- eq (6): Y = Y0 + T + T^2 + T^3 + dT + dT^2 + dT^3 + T*dT + T^2*dT + T*dT^2
  + T^3*dT + T*dT^3 (12 terms incl. Y0), terms chosen by bidirectional stepwise regression (entry by a
  partial F = t^2 test, removal by t-test, as MATLAB ``stepwisefit``: p_enter 0.05, p_remove 0.10).
  Here ``T`` is the *centred* temperature T - T0 (T0 declared, default mid-range; calibration-notes
  lesson 2).

  Validity of the tests on autocorrelated data (calibration-notes 4.1 and lesson 3): the default
  ``test="decimate"`` fits the full 12-term model once, estimates the lag-1 autocorrelation rho of its
  residuals (per run), and block-averages every run into blocks of k = ceil((1 + rho) / (1 - rho))
  points (the AR(1) integrated autocorrelation time, i.e. about one point per noise correlation time;
  never across a run boundary; k is reduced if fewer than 3 points per candidate would remain)
  before the OLS entry/removal t-tests.  Entry is Sidak-corrected over the m candidates tried at a
  step (p_min < 1 - (1 - p_enter)^(1/m)), so the chance that *some* junk term enters a step stays
  at p_enter; ``sidak=False`` gives MATLAB's per-candidate rule.

  Why decimation and not HAC: on our synthetic start-up runs (8 runs x 72 100-s points, AR(1)
  rho = 0.8-0.9 per 100 s) Newey-West/Andrews-bandwidth HAC t-tests (even with Kiefer-Vogelsang
  fixed-b critical values) rejected a true null ~15 % of the time at nominal 5 % (plain OLS: 40-48 %),
  block-averaged OLS tests 3-7 %.  Over 12 seeds (rho = 0.9) stepwise with decimation found the exact
  true set 9 times with 3 junk entries in total; HAC: 4 times / 9 junk; plain OLS: 0 times / 41 junk.
  Also available: ``test="hac"`` (statsmodels OLS cov_type="HAC", maxlags = max(Newey-West
  floor(4 (n/100)^(2/9)), Andrews AR(1) plug-in)), ``test="prewhiten"`` (Cochrane-Orcutt
  quasi-differencing with the same rho; similar to decimation on AR(1) noise) and ``test="ols"``
  (plain p-values; NOT valid on autocorrelated data, kept to demonstrate the problem).
  Final coefficients are refitted by OLS on all 100-s points.

* ``fog_delaunay`` -- section 2.2: 2-D piecewise-linear interpolation of the bias over a Delaunay
  triangulation of selected (T, dT) points (eqs 13-19 are barycentric linear interpolation).  Point
  selection follows the paper: in the fast start-up phase every 100-s point is kept, when the
  temperature changes slowly only every ``stride``-th (paper: "every 2-3") point; then points falling
  into the same cell of a fine grid over the rescaled plane are averaged (removes duplicates that
  would give degenerate triangles).  Axes are rescaled to their ranges before triangulation
  (``rescale=True`` semantics; deg C and deg C/min are incommensurable).  Outside the convex hull the
  value is that of the nearest point of the hull boundary (linear along the nearest hull edge) and
  the sample is flagged (unless within ``hull_tolerance`` = 1 % of the axis ranges, which absorbs the
  difference between the per-sample smoothed inputs and the averaged fit points) -- never NaN,
  never extrapolated.  The hull polygon is stored in ``validity["hull"]``.

Run splitting, 100-s block means, the smoothed rate (method ``"savgol2"``, named in every result's
definition as ``rate_method``) and the lag-1 autocorrelation come from ``bench.signal``.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import ConvexHull, Delaunay, QhullError

from bench.errors import DataFormatError
from bench.fit.base import Dataset, FitResult
from bench.signal import block_means, lag1_autocorrelation, newey_west_lags, run_segments, smoothed_temperature_and_rate

RATE_METHOD = "savgol2"        # bench.signal.temperature_rate method of every dT/dt in these models

def pick_temperature_column(dataset: Dataset, probe: str | None, where: str) -> str:
    """Resolve a probe name ("t2" or "temp_t2"); default: the only temp_* column."""
    if probe:
        name = probe if probe.startswith("temp_") else f"temp_{probe}"
        if name not in dataset:
            raise DataFormatError(f"{where}: temperature column {name!r} not in data "
                                  f"(have: {', '.join(sorted(dataset.columns))})", column=name)
        return name
    temps = [f"temp_{n}" for n in dataset.temp_names()]
    if len(temps) == 1:
        return temps[0]
    raise DataFormatError(f"{where}: choose the temperature probe with probe=... "
                          f"(temperature columns: {', '.join(temps) or 'none'})", column="temp_*")


def _column(dataset: Dataset, name: str, where: str) -> np.ndarray:
    if name not in dataset:
        raise DataFormatError(f"{where}: column {name!r} not in data (have: {', '.join(sorted(dataset.columns))})",
                              column=name)
    values = np.asarray(dataset[name], float)
    bad = ~np.isfinite(values)
    if bad.any():
        raise DataFormatError(f"{where}: {int(bad.sum())} non-finite values in column {name!r} "
                              f"(first at row {int(np.argmax(bad))})", column=name)
    return values


def thermal_inputs(dataset: Dataset, channel: str, temp_column: str, average_s: float, where: str,
                   run_column: str = "run") -> dict[str, Any]:
    """100-s averaged (time, T, dT/dt in C/min, bias) of one channel, per run segment."""
    t = _column(dataset, "time_s", where)
    temp = _column(dataset, temp_column, where)
    y = _column(dataset, f"gyro_{channel}", where)
    run = dataset.columns.get(run_column)
    segs = run_segments(t, run)
    tb, cols, segb, _ = block_means(t, {"T": temp, "y": y}, average_s, segs)
    smooth, rate = smoothed_temperature_and_rate(tb, cols["T"], average_s, segb)
    return {"time_s": tb, "T": cols["T"], "rate": rate, "y": cols["y"], "segments": segb}


def per_sample_thermal(dataset: Dataset, temp: np.ndarray, average_s: float,
                       run_column: str = "run") -> tuple[np.ndarray, np.ndarray]:
    """Smoothed T and dT/dt (C/min) at every sample (prediction side of ``thermal_inputs``)."""
    t = _column(dataset, "time_s", "prediction")
    segs = run_segments(t, dataset.columns.get(run_column))
    return smoothed_temperature_and_rate(t, temp, average_s, segs)


def thermal_validity(dataset: Dataset, temp_samples: np.ndarray, average_s: float, T_avg: np.ndarray,
                     rate_avg: np.ndarray) -> dict[str, float]:
    """T and dT/dt ranges covering both the averaged fit points and the per-sample smoothed values the
    prediction side computes on the same data (so training samples on a soak plateau are not flagged)."""
    Ts, rs = per_sample_thermal(dataset, temp_samples, average_s)
    return {"tmin_c": float(min(T_avg.min(), Ts.min())), "tmax_c": float(max(T_avg.max(), Ts.max())),
            "dtdt_min_c_per_min": float(min(rate_avg.min(), rs.min())),
            "dtdt_max_c_per_min": float(max(rate_avg.max(), rs.max()))}


def apply_mode(values: np.ndarray, flagged: np.ndarray, opts: dict[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    """Registry convention: mode="clip" (default) keeps the clamped values, mode="nan" blanks flagged ones."""
    mode = opts.get("mode", "clip")
    unknown = set(opts) - {"mode"}
    if unknown:
        raise DataFormatError(f"{where}: unknown prediction options {sorted(unknown)}", column=sorted(unknown)[0])
    if mode == "nan":
        return np.where(flagged, np.nan, values), flagged
    if mode != "clip":
        raise DataFormatError(f"{where}: mode must be 'clip' or 'nan', got {mode!r}", column="mode")
    return values, flagged


# --------------------------------------------------------------------------------------------
# 12-term stepwise regression (eq 6)
# --------------------------------------------------------------------------------------------

#: eq (6) candidates as (name, power of T, power of dT); Y0 is always in the model.
FOG_TERMS: tuple[tuple[str, int, int], ...] = (
    ("T", 1, 0), ("T^2", 2, 0), ("T^3", 3, 0),
    ("dT", 0, 1), ("dT^2", 0, 2), ("dT^3", 0, 3),
    ("T*dT", 1, 1), ("T^2*dT", 2, 1), ("T*dT^2", 1, 2), ("T^3*dT", 3, 1), ("T*dT^3", 1, 3),
)
_TERM_POWERS = {name: (p, q) for name, p, q in FOG_TERMS}


def fog_design(x_c: np.ndarray, rate: np.ndarray, names: list[str]) -> np.ndarray:
    """Columns [1, term...] for centred temperature ``x_c`` (C) and rate (C/min)."""
    cols = [np.ones_like(x_c)]
    for name in names:
        p, q = _TERM_POWERS[name]
        cols.append(x_c ** p * rate ** q)
    return np.column_stack(cols)


def _andrews_maxlags(resid: np.ndarray) -> int:
    n = resid.size
    nw = newey_west_lags(n)
    rho = lag1_autocorrelation(resid) if n > 2 else 0.0
    rho = min(max(rho, 0.0), 0.97)
    alpha = 4 * rho ** 2 / ((1 - rho) ** 2 * (1 + rho) ** 2)
    andrews = int(math.ceil(1.1447 * (alpha * n) ** (1.0 / 3.0))) if rho > 0 else 0
    return max(1, min(max(nw, andrews), n // 4))


def _pvalues(y: np.ndarray, X: np.ndarray, test: str) -> np.ndarray:
    """p-values of all columns except the constant, on column-standardised X."""
    import statsmodels.api as sm

    scale = X.std(axis=0)
    scale[0] = 1.0
    scale[scale == 0] = 1.0
    Xs = X / scale
    if test == "hac":
        ols = sm.OLS(y, Xs).fit()
        res = sm.OLS(y, Xs).fit(cov_type="HAC", cov_kwds={"maxlags": _andrews_maxlags(ols.resid)}, use_t=True)
    else:
        res = sm.OLS(y, Xs).fit()
    p = np.asarray(res.pvalues, float)[1:]
    return np.where(np.isfinite(p), p, 1.0)


def stepwise_select(x_c: np.ndarray, rate: np.ndarray, y: np.ndarray, segments: list[slice], *,
                    test: str = "decimate", p_enter: float = 0.05, p_remove: float = 0.10,
                    candidates: list[str] | None = None, sidak: bool = True,
                    max_steps: int = 100) -> dict[str, Any]:
    """Bidirectional stepwise selection over the eq-6 candidates.  Returns selected terms,
    p-values of the final model (on the tested data), and the decimation used."""
    if test not in ("decimate", "prewhiten", "hac", "ols"):
        raise DataFormatError(f"fog_stepwise: test must be 'decimate', 'prewhiten', 'hac' or 'ols', got {test!r}",
                              column="test")
    if not (0 < p_enter < p_remove < 1):
        raise DataFormatError(f"fog_stepwise: need 0 < p_enter < p_remove < 1, got {p_enter}, {p_remove}",
                              column="p_enter")
    names = list(candidates) if candidates is not None else [n for n, _, _ in FOG_TERMS]
    unknown = [n for n in names if n not in _TERM_POWERS]
    if unknown:
        raise DataFormatError(f"fog_stepwise: unknown candidate terms {unknown}", column="candidates")
    full = fog_design(x_c, rate, names)
    if y.size < 2 * full.shape[1]:
        raise DataFormatError(f"fog_stepwise: {y.size} averaged points for {full.shape[1]} terms; need at least "
                              f"{2 * full.shape[1]}", column="time_s")
    coef, *_ = np.linalg.lstsq(full, y, rcond=None)
    rho = lag1_autocorrelation(y - full @ coef, segments)
    block = 1
    X_all, y_test = full, y
    if test == "decimate":
        block = max(1, int(math.ceil((1 + max(rho, 0.0)) / max(1 - rho, 1e-3))))
        min_points = 3 * full.shape[1]
        while block > 1 and sum(s.stop - s.start for s in segments) // block < min_points:
            block -= 1
        if block > 1:
            idx = np.arange(y.size, dtype=float)
            cols = {f"c{j}": full[:, j] for j in range(full.shape[1])}
            cols["y"] = y
            avg = block_means(idx, cols, float(block), segments).columns
            X_all = np.column_stack([avg[f"c{j}"] for j in range(full.shape[1])])
            y_test = avg["y"]
    if test == "prewhiten":
        # Cochrane-Orcutt quasi-differencing inside each run: e_t - rho e_{t-1} is white for AR(1) noise
        rows = np.concatenate([np.arange(sg.start + 1, sg.stop) for sg in segments if sg.stop - sg.start > 1])
        X_all = full[rows] - rho * full[rows - 1]
        y_test = y[rows] - rho * y[rows - 1]
    base_test = "ols" if test in ("decimate", "prewhiten") else test
    chosen: list[int] = []
    trace: list[str] = []
    for _ in range(max_steps):
        changed = False
        remaining = [j for j in range(len(names)) if j not in chosen]
        best_j, best_p = None, 1.0
        for j in remaining:
            X = X_all[:, [0] + [c + 1 for c in chosen + [j]]]
            p = _pvalues(y_test, X, base_test)[-1]
            if p < best_p:
                best_j, best_p = j, p
        # Sidak: the smallest of m candidate p-values is compared with 1 - (1 - p_enter)^(1/m), so the
        # chance that *some* junk candidate enters at this step stays at p_enter.
        threshold = 1.0 - (1.0 - p_enter) ** (1.0 / len(remaining)) if (remaining and sidak) else p_enter
        if best_j is not None and best_p < threshold:
            chosen.append(best_j)
            trace.append(f"+{names[best_j]} (p={best_p:.3g})")
            changed = True
        if chosen:
            p = _pvalues(y_test, X_all[:, [0] + [c + 1 for c in chosen]], base_test)
            worst = int(np.argmax(p))
            if p[worst] > p_remove:
                trace.append(f"-{names[chosen[worst]]} (p={p[worst]:.3g})")
                chosen.pop(worst)
                changed = True
        if not changed:
            break
    selected = [names[j] for j in sorted(chosen)]
    final_p = (_pvalues(y_test, X_all[:, [0] + [j + 1 for j in sorted(chosen)]], base_test)
               if chosen else np.zeros(0))
    return {"selected": selected, "pvalues": dict(zip(selected, map(float, final_p))), "rho_lag1": rho,
            "block": block, "n_tested": int(y_test.size), "trace": trace, "test": test}


def _t0_default(T: np.ndarray) -> float:
    return round(0.5 * (float(T.min()) + float(T.max())), 2)


def fit_fog_stepwise(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """Options: probe ("t1"), average_s (100), t0_c (mid-range), test ("decimate"|"prewhiten"|"hac"|"ols"),
    p_enter (0.05), p_remove (0.10), sidak (True), candidates (subset of FOG_TERMS names)."""
    where = f"fog_stepwise gyro_{channel}"
    temp_col = pick_temperature_column(dataset, opts.get("probe"), where)
    average_s = float(opts.get("average_s", 100.0))
    data = thermal_inputs(dataset, channel, temp_col, average_s, where)
    T, rate, y = data["T"], data["rate"], data["y"]
    t0 = float(opts.get("t0_c", _t0_default(T)))
    sel = stepwise_select(T - t0, rate, y, data["segments"], test=opts.get("test", "decimate"),
                          p_enter=float(opts.get("p_enter", 0.05)), p_remove=float(opts.get("p_remove", 0.10)),
                          candidates=opts.get("candidates"), sidak=bool(opts.get("sidak", True)))
    terms = sel["selected"]
    X = fog_design(T - t0, rate, terms)
    scale = X.std(axis=0)
    scale[0] = 1.0
    scale[scale == 0] = 1.0
    beta_s, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    beta = beta_s / scale
    resid = y - X @ beta
    names = ["Y0"] + terms
    units = {"Y0": "deg/h"}
    for name in terms:
        p, q = _TERM_POWERS[name]
        parts = ([f"C^{p}" if p > 1 else "C"] if p else []) + ([f"(C/min)^{q}" if q > 1 else "C/min"] if q else [])
        units[name] = "deg/h/(" + "*".join(parts) + ")"
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return FitResult(
        model="fog_stepwise", channel=channel, target=f"gyro_{channel}",
        definition={
            "formula": "Y = Y0 + sum_k c_k * T^p_k * dT^q_k; T = temp - t0_c (C), dT = dT/dt (C/min)",
            "source": "seed 004 eq 6 (12 candidate terms incl. Y0), stepwise selection",
            "terms": [{"name": n, "T_power": _TERM_POWERS[n][0], "dT_power": _TERM_POWERS[n][1]} for n in terms],
            "t0_c": t0, "temperature_column": temp_col, "average_s": average_s,
            "rate_method": RATE_METHOD, "rate_window_s": average_s,
            "rate_filter": f"Savitzky-Golay order 2 over {average_s:g} s (gradient on {average_s:g}-s means)",
            "selection": {"test": sel["test"], "p_enter": float(opts.get("p_enter", 0.05)),
                          "p_remove": float(opts.get("p_remove", 0.10)), "block_points": sel["block"],
                          "sidak_entry": bool(opts.get("sidak", True)),
                          "rho_lag1_full_model": sel["rho_lag1"], "trace": sel["trace"]},
        },
        coefficients={n: float(b) for n, b in zip(names, beta)},
        units=units,
        validity=thermal_validity(dataset, dataset[temp_col], average_s, T, rate),
        stats={"n": int(y.size), "n_tested": sel["n_tested"], "rms_dph": float(np.sqrt(np.mean(resid ** 2))),
               "r2": 1.0 - float(np.sum(resid ** 2)) / ss_tot if ss_tot > 0 else float("nan"),
               "cond": float(np.linalg.cond(X / scale)), "pvalues": sel["pvalues"]},
    )


def predict_fog_stepwise(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """Bias at every sample; T and dT/dt outside the fitted ranges are clipped and flagged."""
    d = result.definition
    temp = _column(dataset, d["temperature_column"], "fog_stepwise prediction")
    T, rate = per_sample_thermal(dataset, temp, float(d["average_s"]))
    v = result.validity
    Tc = np.clip(T, v["tmin_c"], v["tmax_c"])
    rc = np.clip(rate, v["dtdt_min_c_per_min"], v["dtdt_max_c_per_min"])
    flagged = (Tc != T) | (rc != rate)
    terms = [t["name"] for t in d["terms"]]
    X = fog_design(Tc - float(d["t0_c"]), rc, terms)
    beta = np.array([result.coefficients["Y0"]] + [result.coefficients[n] for n in terms])
    return apply_mode(X @ beta, flagged, opts, "fog_stepwise prediction")


# --------------------------------------------------------------------------------------------
# 2-D Delaunay linear interpolation over (T, dT/dt)
# --------------------------------------------------------------------------------------------


def select_points(T: np.ndarray, rate: np.ndarray, y: np.ndarray, segments: list[slice], *,
                  stride: int = 3, fast_fraction: float = 0.1, grid: int = 200) -> np.ndarray:
    """Paper's point choice, then grid de-duplication.  Returns rows (T, dT/dt, bias).

    Inside each run: points with |dT/dt| >= fast_fraction * max|dT/dt| of that run (start-up) are all
    kept, slower ones every ``stride``-th.  Then points in the same cell of a grid x grid raster over
    the rescaled plane are averaged."""
    if stride < 1 or grid < 2:
        raise DataFormatError(f"fog_delaunay: stride >= 1 and grid >= 2 required, got {stride}, {grid}",
                              column="stride")
    keep = np.zeros(T.size, bool)
    for seg in segments:
        r = np.abs(rate[seg])
        fast = r >= fast_fraction * (r.max() if r.size else 0.0)
        slow_idx = np.nonzero(~fast)[0]
        k = fast.copy()
        k[slow_idx[::stride]] = True
        keep[seg] = k
    pts = np.column_stack([T[keep], rate[keep], y[keep]])
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    cell = np.minimum(((pts[:, :2] - lo) / span * grid).astype(np.int64), grid - 1)
    key = cell[:, 0] * grid + cell[:, 1]
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return np.column_stack([np.bincount(inverse, weights=pts[:, j], minlength=uniq.size) / counts
                            for j in range(3)])


class DelaunaySurface:
    """Piecewise-linear bias surface over rescaled (T, dT/dt) with explicit out-of-hull handling."""

    def __init__(self, points: np.ndarray, values: np.ndarray, centre: np.ndarray, scale: np.ndarray,
                 tolerance: float = 0.0) -> None:
        """``tolerance``: distance outside the hull, in rescaled units (fractions of the axis ranges),
        still treated as inside (value from the hull boundary, not flagged)."""
        self.tolerance = float(tolerance)
        self.points = np.asarray(points, float)
        self.values = np.asarray(values, float)
        self.centre = np.asarray(centre, float)
        self.scale = np.asarray(scale, float)
        scaled = (self.points - self.centre) / self.scale
        try:
            self.tri = Delaunay(scaled)
        except QhullError as exc:
            raise DataFormatError(f"fog_delaunay: cannot triangulate {len(points)} (T, dT/dt) points "
                                  f"(all collinear or too few): {str(exc).splitlines()[0]}", column="temp") from None
        self.interp = LinearNDInterpolator(self.tri, self.values)
        edges = self.tri.convex_hull                       # (E, 2) vertex indices of hull edges
        self._a = scaled[edges[:, 0]]
        self._b = scaled[edges[:, 1]]
        self._va = self.values[edges[:, 0]]
        self._vb = self.values[edges[:, 1]]

    def hull_vertices(self) -> np.ndarray:
        """Hull polygon (counter-clockwise) in physical units."""
        hull = ConvexHull((self.points - self.centre) / self.scale)
        return self.points[hull.vertices]

    def __call__(self, T: np.ndarray, rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = (np.column_stack([np.asarray(T, float), np.asarray(rate, float)]) - self.centre) / self.scale
        inside = self.tri.find_simplex(q) >= 0
        values = np.empty(q.shape[0])
        if inside.any():
            values[inside] = self.interp(q[inside])
        # points find_simplex accepts but the interpolator returns NaN for (round-off on an edge) and
        # points outside the hull: value of the nearest hull-boundary point.
        needs = ~inside | ~np.isfinite(values)
        flagged = np.zeros(q.shape[0], bool)
        if needs.any():
            values[needs], dist = self._nearest_boundary_value(q[needs])
            flagged[needs] = ~inside[needs] & (dist > self.tolerance)
        return values, flagged

    def _nearest_boundary_value(self, q: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        out = np.empty(q.shape[0])
        out_dist = np.empty(q.shape[0])
        ab = self._b - self._a
        ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        for start in range(0, q.shape[0], chunk):
            qq = q[start:start + chunk, None, :]                         # (m, 1, 2)
            t = np.clip(np.einsum("mej,ej->me", qq - self._a, ab) / ab2, 0.0, 1.0)
            proj = self._a + t[..., None] * ab
            dist = np.einsum("mej,mej->me", qq - proj, qq - proj)
            e = np.argmin(dist, axis=1)
            tt = t[np.arange(e.size), e]
            out[start:start + chunk] = (1 - tt) * self._va[e] + tt * self._vb[e]
            out_dist[start:start + chunk] = np.sqrt(dist[np.arange(e.size), e])
        return out, out_dist


def fit_fog_delaunay(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """Options: probe, average_s (100), stride (3), fast_fraction (0.1), grid (200), hull_tolerance
    (0.01 of the axis ranges: samples that close to the hull are not flagged)."""
    where = f"fog_delaunay gyro_{channel}"
    temp_col = pick_temperature_column(dataset, opts.get("probe"), where)
    average_s = float(opts.get("average_s", 100.0))
    data = thermal_inputs(dataset, channel, temp_col, average_s, where)
    pts = select_points(data["T"], data["rate"], data["y"], data["segments"],
                        stride=int(opts.get("stride", 3)), fast_fraction=float(opts.get("fast_fraction", 0.1)),
                        grid=int(opts.get("grid", 200)))
    if pts.shape[0] < 3:
        raise DataFormatError(f"{where}: only {pts.shape[0]} distinct (T, dT/dt) points; need >= 3", column=temp_col)
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    centre = 0.5 * (lo + hi)
    scale = np.where(hi > lo, hi - lo, 1.0)
    tolerance = float(opts.get("hull_tolerance", 0.01))
    surface = DelaunaySurface(pts[:, :2], pts[:, 2], centre, scale, tolerance)
    fitted, _ = surface(data["T"], data["rate"])
    resid = data["y"] - fitted
    return FitResult(
        model="fog_delaunay", channel=channel, target=f"gyro_{channel}",
        definition={
            "formula": "piecewise-linear (barycentric) interpolation of bias over a Delaunay triangulation of "
                       "(T, dT/dt) scaled as (x - centre) / scale; outside the hull: value at the nearest hull "
                       "boundary point, flagged",
            "source": "seed 004 section 2.2, eqs 13-19",
            "temperature_column": temp_col, "average_s": average_s,
            "rate_method": RATE_METHOD, "rate_window_s": average_s,
            "centre": centre.tolist(), "scale": scale.tolist(), "hull_tolerance": tolerance,
            "points": pts.tolist(),                            # rows: T (C), dT/dt (C/min), bias (deg/h)
            "selection": {"stride": int(opts.get("stride", 3)), "fast_fraction": float(opts.get("fast_fraction", 0.1)),
                          "grid": int(opts.get("grid", 200))},
        },
        coefficients={},
        units={"T": "C", "dT/dt": "C/min", "bias": "deg/h"},
        validity={"tmin_c": float(lo[0]), "tmax_c": float(hi[0]), "dtdt_min_c_per_min": float(lo[1]),
                  "dtdt_max_c_per_min": float(hi[1]), "hull": surface.hull_vertices().tolist()},
        stats={"n": int(data["y"].size), "n_points": int(pts.shape[0]), "n_triangles": int(len(surface.tri.simplices)),
               "rms_dph": float(np.sqrt(np.mean(resid ** 2)))},
    )


def surface_from_result(result: FitResult) -> DelaunaySurface:
    d = result.definition
    pts = np.asarray(d["points"], float)
    return DelaunaySurface(pts[:, :2], pts[:, 2], np.asarray(d["centre"]), np.asarray(d["scale"]),
                           float(d.get("hull_tolerance", 0.0)))


def predict_fog_delaunay(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """Bias at every sample; flagged where (T, dT/dt) lies outside the hull (value clamped to the hull)."""
    d = result.definition
    temp = _column(dataset, d["temperature_column"], "fog_delaunay prediction")
    T, rate = per_sample_thermal(dataset, temp, float(d["average_s"]))
    values, flagged = surface_from_result(result)(T, rate)
    return apply_mode(values, flagged, opts, "fog_delaunay prediction")
