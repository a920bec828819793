"""HRG models of seed 002 (DONG et al. 2023, HRG temperature compensation with PSO).

* Forward cubic f(T) (eqs 1, 2): resonance frequency (Hz) of a gyro against its reference temperature
  (paper: the DS18B20 on the case, T2).  Fitted in centred/scaled temperature for conditioning and
  also returned expanded in the paper's raw-T basis (c3 T^3 + c2 T^2 + c1 T + c0) for comparison.
  ``ForwardCubic.solve`` gives the paper's "forward solution" T3 (real root of f(T) = f nearest to
  the calibrated range, the job Matlab ``roots`` did in the paper).
* Reverse cubic T(f) (section 2.2, "逆向拟合"): temperature directly from frequency.  The paper prints
  T(f) = a f^3 + b f^2 + c f + d with 4 significant digits, which cannot be evaluated (f ~ 4900 Hz:
  the terms cancel over ~12 orders of magnitude, see the comment lines of
  reference/hrg_reverse_fit_gx.csv).  We fit T = a0 + a1 u + a2 u^2 + a3 u^3 with
  u = (f - f_centre_hz) / f_scale_hz (centre = mid-range, scale = half-range, so |u| <= 1 on the
  calibrated range); firmware evaluates exactly that with the stored centre/scale.
* Bias model eq (7): B = k0 + k1 T + k2 T^2 + k3 dT + k4 dT^2 + k5 T dT, T in deg C (by default the
  temperature solved from the frequency with the reverse cubic, as in the paper's section 4), dT the
  rate in deg C/min of the 100-s smoothed temperature.  Fitted by least squares (``hrg``) and by PSO
  with the paper's settings (``hrg_pso``: 200 particles, 200 iterations, c1 = c2 = 1.5, w = 0.8,
  fitness eq (8) = sum of squared errors).

PSO honesty (calibration-notes 4.3 and lesson 10): eq (7) is *linear in k*, so least squares is the
global minimum of eq (8); PSO can at best equal it.  ``hrg_pso`` therefore reports both costs, runs
PSO both seeded with the LS solution and unseeded, and reports the condition number of the design.
PSO searches standardised coefficients (regressors centred/scaled, bias scaled to unit std) inside
[-bound, bound] (paper: [-1, 1]; default here 3 because standardised LS coefficients can exceed 1).
The squared-error cost is evaluated exactly through a QR compression of the data
(||y - X k||^2 = ||y_perp||^2 + ||Q'y - R k||^2), which makes 40 000 evaluations on 10^5 samples
cheap; the final PSO cost is re-checked directly on the data.  Measured (tests/perf/pso.py, 10^5
samples, cool/soak/heat profile): LS-seeded PSO = LS cost exactly; unseeded PSO with the paper's
settings stalls 0.4-1.5 % above it (gbest PSO is slow in the correlated valley of T*dT vs dT and
T^2 vs 1; standardised condition number ~20, raw ~4e4) -- the design, not the optimiser, limits.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.errors import DataFormatError
from bench.fit import pso
from bench.fit.base import Dataset, FitResult, channel_probe, channel_probe_map
from bench.fit.fog import (
    RATE_METHOD,
    _column,
    apply_mode,
    per_sample_thermal,
    pick_temperature_column,
    thermal_validity,
)
from bench.signal import block_means, run_segments, temperature_rate

# --------------------------------------------------------------------------------------------
# Frequency <-> temperature cubics
# --------------------------------------------------------------------------------------------


def _centre_scale(x: np.ndarray) -> tuple[float, float]:
    lo, hi = float(np.min(x)), float(np.max(x))
    return 0.5 * (lo + hi), (0.5 * (hi - lo) if hi > lo else 1.0)


def _fit_cubic(x: np.ndarray, y: np.ndarray, what: str) -> tuple[float, float, np.ndarray, float]:
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if x.shape != y.shape or x.ndim != 1:
        raise DataFormatError(f"{what}: need two equal-length 1-D arrays, got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise DataFormatError(f"{what}: non-finite input values")
    if np.unique(x).size < 4:
        raise DataFormatError(f"{what}: a cubic needs at least 4 distinct abscissae, got {np.unique(x).size}")
    centre, scale = _centre_scale(x)
    V = np.vander((x - centre) / scale, 4, increasing=True)
    coef, *_ = np.linalg.lstsq(V, y, rcond=None)
    return centre, scale, coef, float(np.linalg.cond(V))


@dataclass(frozen=True)
class ScaledCubic:
    """y(x) = c0 + c1 u + c2 u^2 + c3 u^3, u = (x - centre) / scale, calibrated for lo <= x <= hi."""

    centre: float
    scale: float
    coeffs: tuple[float, float, float, float]
    lo: float
    hi: float

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        u = (np.asarray(x, float) - self.centre) / self.scale
        return np.polynomial.polynomial.polyval(u, self.coeffs)

    def evaluate_clipped(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values with x clipped to [lo, hi], and where it was clipped."""
        f = np.asarray(x, float)
        fc = np.clip(f, self.lo, self.hi)
        return self.evaluate(fc), fc != f


class ReverseCubic(ScaledCubic):
    """T(f) in C of the resonance frequency f in Hz (centre, scale, lo, hi in Hz)."""


def fit_reverse_cubic(freq_hz: np.ndarray, temp_c: np.ndarray) -> ReverseCubic:
    centre, scale, coef, _ = _fit_cubic(freq_hz, temp_c, "HRG reverse cubic T(f)")
    f = np.asarray(freq_hz, float)
    return ReverseCubic(centre, scale, tuple(float(c) for c in coef), float(f.min()), float(f.max()))


class ForwardCubic(ScaledCubic):
    """f(T) in Hz of the temperature T in C (centre, scale, lo, hi in C)."""

    def raw_coefficients(self) -> dict[str, float]:
        """Expansion in raw T: f = c3 T^3 + c2 T^2 + c1 T + c0 (the paper's eq-2 form)."""
        shifted = np.polynomial.Polynomial(self.coeffs)(np.polynomial.Polynomial([-self.centre / self.scale,
                                                                                  1.0 / self.scale]))
        c = np.zeros(4)
        c[: shifted.coef.size] = shifted.coef
        return {"c0": float(c[0]), "c1": float(c[1]), "c2": float(c[2]), "c3": float(c[3])}

    def solve(self, freq_hz: np.ndarray) -> np.ndarray:
        """Forward solution T3: the real root of f(T) = freq nearest the calibrated range centre."""
        out = np.empty(np.size(freq_hz))
        for i, f in enumerate(np.ravel(np.asarray(freq_hz, float))):
            c = np.array(self.coeffs, float)
            c[0] -= f
            roots = np.polynomial.polynomial.polyroots(c)
            real = roots[np.abs(roots.imag) <= 1e-9 * max(1.0, np.abs(roots).max())].real
            if real.size == 0:
                raise DataFormatError(f"HRG forward cubic: no real temperature for f = {f} Hz")
            out[i] = self.centre + self.scale * real[np.argmin(np.abs(real))]
        return out.reshape(np.shape(freq_hz))


def fit_forward_cubic(temp_c: np.ndarray, freq_hz: np.ndarray) -> ForwardCubic:
    centre, scale, coef, _ = _fit_cubic(temp_c, freq_hz, "HRG forward cubic f(T)")
    t = np.asarray(temp_c, float)
    return ForwardCubic(centre, scale, tuple(float(c) for c in coef), float(t.min()), float(t.max()))


# --------------------------------------------------------------------------------------------
# Eq (7) bias model: least squares and PSO
# --------------------------------------------------------------------------------------------

EQ7_TERMS = ("k0", "k1", "k2", "k3", "k4", "k5")
EQ7_UNITS = {"k0": "deg/h", "k1": "deg/h/C", "k2": "deg/h/C^2", "k3": "deg/h/(C/min)",
             "k4": "deg/h/(C/min)^2", "k5": "deg/h/(C*C/min)"}


def eq7_design(T: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """Raw-basis eq-7 columns [1, T, T^2, dT, dT^2, T*dT]."""
    T = np.asarray(T, float)
    r = np.asarray(rate, float)
    return np.column_stack([np.ones_like(T), T, T ** 2, r, r ** 2, T * r])


@dataclass
class Eq7Problem:
    """Standardised eq-7 regression: y_s = (y - y_mean)/y_std ~ D(u, v) theta with u, v the centred and
    scaled T and dT; ``to_raw`` maps theta back to k0..k5 of eq 7 in deg C, deg C/min, deg/h."""

    T: np.ndarray
    rate: np.ndarray
    y: np.ndarray

    def __post_init__(self) -> None:
        T, r, y = (np.asarray(a, float) for a in (self.T, self.rate, self.y))
        if not (T.shape == r.shape == y.shape) or T.ndim != 1:
            raise DataFormatError(f"HRG eq 7: T, dT/dt and bias must be equal-length 1-D arrays, "
                                  f"got {T.shape}, {r.shape}, {y.shape}")
        if T.size < 12:
            raise DataFormatError(f"HRG eq 7: {T.size} points for 6 coefficients; need at least 12")
        self.tc, self.ts = float(T.mean()), float(T.std()) or 1.0
        self.rc, self.rs = float(r.mean()), float(r.std()) or 1.0
        self.ym, self.ys = float(y.mean()), float(y.std()) or 1.0
        X = eq7_design((T - self.tc) / self.ts, (r - self.rc) / self.rs)
        yn = (y - self.ym) / self.ys
        Q, R = np.linalg.qr(X)
        self.R = R
        self.z = Q.T @ yn
        self.rss_perp = max(float(yn @ yn - self.z @ self.z), 0.0)
        self.cond = float(np.linalg.cond(R))
        self.cond_raw = float(np.linalg.cond(eq7_design(T, r)))
        self.n = T.size
        # theta (standardised) -> k (raw): exact, both designs span the same polynomial space
        gu, gv = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
        Tg, rg = self.tc + self.ts * gu.ravel(), self.rc + self.rs * gv.ravel()
        self._map = np.linalg.lstsq(eq7_design(Tg, rg), eq7_design(gu.ravel(), gv.ravel()), rcond=None)[0]

    def cost_std(self, thetas: np.ndarray) -> np.ndarray:
        """Eq-8 cost in standardised units for a batch of theta rows (exact via QR)."""
        diff = self.z[None, :] - np.atleast_2d(thetas) @ self.R.T
        return self.rss_perp + np.einsum("ij,ij->i", diff, diff)

    def solve_ls(self) -> np.ndarray:
        return np.linalg.solve(self.R, self.z)

    def to_raw(self, theta: np.ndarray) -> np.ndarray:
        k = self._map @ (self.ys * np.asarray(theta, float))
        k[0] += self.ym
        return k

    def sse_raw(self, k: np.ndarray) -> float:
        """Eq (8) evaluated directly on the data, (deg/h)^2."""
        e = np.asarray(self.y, float) - eq7_design(self.T, self.rate) @ k
        return float(e @ e)


def fit_eq7_ls(T: np.ndarray, rate: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    prob = Eq7Problem(T, rate, y)
    k = prob.to_raw(prob.solve_ls())
    return k, {"cost": prob.sse_raw(k), "cond_std": prob.cond, "cond_raw": prob.cond_raw}


def fit_eq7_pso(T: np.ndarray, rate: np.ndarray, y: np.ndarray, *, settings: pso.PsoSettings = pso.PsoSettings(),
                bound: float = 3.0, seed_with_ls: bool = True) -> tuple[np.ndarray, dict[str, Any]]:
    """PSO on eq (8).  Returns raw k and a report with PSO and LS costs (both in (deg/h)^2)."""
    if not bound > 0:
        raise DataFormatError(f"HRG PSO: bound must be > 0, got {bound}", column="bound")
    prob = Eq7Problem(T, rate, y)
    theta_ls = prob.solve_ls()
    lower, upper = np.full(6, -bound), np.full(6, bound)
    res = pso.minimize(prob.cost_std, lower, upper, settings=settings,
                       initial=theta_ls if seed_with_ls else None)
    k = prob.to_raw(res.best_position)
    k_ls = prob.to_raw(theta_ls)
    cost_ls = prob.sse_raw(k_ls)
    cost_pso = prob.sse_raw(k)
    return k, {"cost_pso": cost_pso, "cost_ls": cost_ls, "cost_ratio": cost_pso / cost_ls if cost_ls > 0 else float("inf"),
               "seeded": res.seeded, "at_bound": [EQ7_TERMS[i] for i in np.nonzero(res.at_bound)[0]],
               "ls_outside_bounds": bool(np.any(np.abs(theta_ls) > bound)),
               "history_std": res.history, "n_evaluations": res.n_evaluations,
               "cond_std": prob.cond, "cond_raw": prob.cond_raw}


# --------------------------------------------------------------------------------------------
# Dataset adapters
# --------------------------------------------------------------------------------------------


def _reverse_from_definition(d: dict[str, Any]) -> ReverseCubic:
    return ReverseCubic(float(d["f_centre_hz"]), float(d["f_scale_hz"]), tuple(float(c) for c in d["coefficients"]),
                        float(d["fmin_hz"]), float(d["fmax_hz"]))


def _reverse_definition(rc: ReverseCubic, freq_column: str) -> dict[str, Any]:
    return {"kind": "reverse_cubic", "freq_column": freq_column, "f_centre_hz": rc.centre,
            "f_scale_hz": rc.scale, "coefficients": list(rc.coeffs), "fmin_hz": rc.lo, "fmax_hz": rc.hi,
            "formula": "T = a0 + a1 u + a2 u^2 + a3 u^3, u = (f - f_centre_hz) / f_scale_hz"}


def _averaged_pair(dataset: Dataset, x: np.ndarray, y: np.ndarray, average_s: float) -> tuple[np.ndarray, np.ndarray]:
    if "time_s" not in dataset or average_s <= 0:
        return x, y
    t = np.asarray(dataset["time_s"], float)
    cols = block_means(t, {"x": x, "y": y}, average_s, run_segments(t, dataset.columns.get("run"))).columns
    return cols["x"], cols["y"]


def _reference_probe(dataset: Dataset, channel: str, opts: dict[str, Any], *keys: str) -> str | None:
    """The temperature probe of a channel: the first of the ``keys`` options given, else the channel's
    own probe when the data's ``channel_probes`` map names it, else None (the only temp_* column)."""
    for key in keys:
        if opts.get(key):
            return opts[key]
    if channel in channel_probe_map(dataset):
        return channel_probe(dataset, channel)
    return None


def _frequency_and_reference(dataset: Dataset, channel: str, opts: dict[str, Any], model: str):
    """(where, freq column, reference temperature column, averaged f (Hz), averaged T (C))."""
    where = f"{model} freq_{channel}"
    fcol = f"freq_{channel}"
    tcol = pick_temperature_column(dataset, _reference_probe(dataset, channel, opts, "reference", "probe"), where)
    f, T = _averaged_pair(dataset, _column(dataset, fcol, where), _column(dataset, tcol, where),
                          float(opts.get("average_s", 100.0)))
    return where, fcol, tcol, f, T


def fit_hrg_reverse(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """T(freq_<ch>) against the reference probe (``reference``/``probe``: e.g. "t2").
    Option average_s (default 100; 0 = use every sample)."""
    where, fcol, tcol, f, T = _frequency_and_reference(dataset, channel, opts, "hrg_reverse")
    rc = fit_reverse_cubic(f, T)
    f_raw = dataset[fcol]       # range of the raw samples, so noisy plateau samples are not flagged
    rc = ReverseCubic(rc.centre, rc.scale, rc.coeffs, float(min(f.min(), f_raw.min())),
                      float(max(f.max(), f_raw.max())))
    err = rc.evaluate(f) - T
    _, _, _, cond = _fit_cubic(f, T, where)
    fwd = fit_forward_cubic(T, f)
    return FitResult(
        model="hrg_reverse", channel=channel, target=tcol,
        definition={**_reverse_definition(rc, fcol), "source": "seed 002 section 2.2 (reverse fit), centred/scaled f",
                    "basis": "centred_scaled_frequency", "reference": tcol,
                    "average_s": float(opts.get("average_s", 100.0))},
        coefficients={f"a{i}": float(c) for i, c in enumerate(rc.coeffs)},
        units={f"a{i}": "C" for i in range(4)} | {"f_centre_hz": "Hz", "f_scale_hz": "Hz"},
        validity={"fmin_hz": rc.lo, "fmax_hz": rc.hi, "tmin_c": float(T.min()), "tmax_c": float(T.max())},
        stats={"n": int(T.size), "rms_c": float(np.sqrt(np.mean(err ** 2))), "max_abs_error_c": float(np.abs(err).max()),
               "cond": cond, "forward_raw_coefficients": fwd.raw_coefficients(),
               "forward_max_abs_error_c": float(np.abs(fwd.solve(f) - T).max())},
    )


def predict_hrg_reverse(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """Temperature from frequency; frequencies outside the calibrated range are clipped and flagged."""
    rc = _reverse_from_definition(result.definition)
    values, flagged = rc.evaluate_clipped(_column(dataset, result.definition["freq_column"], "hrg_reverse prediction"))
    return apply_mode(values, flagged, opts, "hrg_reverse prediction")


def fit_hrg_forward(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """f(T) of eq 2 against the reference probe; coefficients in the paper's raw-T basis (c0..c3)
    plus the centred/scaled ones in the definition."""
    where, fcol, tcol, f, T = _frequency_and_reference(dataset, channel, opts, "hrg_forward")
    fc = fit_forward_cubic(T, f)
    err = fc.evaluate(T) - f
    return FitResult(
        model="hrg_forward", channel=channel, target=fcol,
        definition={"formula": "f = c3 T^3 + c2 T^2 + c1 T + c0 (= b0 + b1 v + b2 v^2 + b3 v^3, v = (T - t_centre_c) "
                               "/ t_scale_c)", "source": "seed 002 eq 2", "temperature_column": tcol,
                    "t_centre_c": fc.centre, "t_scale_c": fc.scale, "scaled_coefficients": list(fc.coeffs),
                    "average_s": float(opts.get("average_s", 100.0))},
        coefficients=fc.raw_coefficients(),
        units={"c0": "Hz", "c1": "Hz/C", "c2": "Hz/C^2", "c3": "Hz/C^3"},
        validity={"tmin_c": fc.lo, "tmax_c": fc.hi},
        stats={"n": int(T.size), "rms_hz": float(np.sqrt(np.mean(err ** 2))),
               "max_abs_error_c": float(np.abs(fc.solve(f) - T).max())},
    )


def predict_hrg_forward(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    d = result.definition
    fc = ForwardCubic(d["t_centre_c"], d["t_scale_c"], tuple(d["scaled_coefficients"]),
                      result.validity["tmin_c"], result.validity["tmax_c"])
    T = _column(dataset, d["temperature_column"], "hrg_forward prediction")
    Tc = np.clip(T, fc.lo, fc.hi)
    return apply_mode(fc.evaluate(Tc), Tc != T, opts, "hrg_forward prediction")


def _temperature_source(dataset: Dataset, channel: str, opts: dict[str, Any], where: str) -> dict[str, Any]:
    reverse = opts.get("reverse")
    if isinstance(reverse, FitResult):
        if reverse.model != "hrg_reverse":
            raise DataFormatError(f"{where}: reverse= must be an hrg_reverse result, got {reverse.model!r}",
                                  column="reverse")
        return _reverse_definition(_reverse_from_definition(reverse.definition), reverse.definition["freq_column"])
    source = opts.get("temperature_source", "freq")
    if source == "freq" and f"freq_{channel}" in dataset:
        reference = _reference_probe(dataset, channel, opts, "reference", "probe")
        rev = fit_hrg_reverse(dataset, channel, reference=reference,
                              average_s=opts.get("average_s", 100.0))
        out = _reverse_definition(_reverse_from_definition(rev.definition), f"freq_{channel}")
        out["fitted_against"] = rev.target
        return out
    if source not in ("freq", "probe"):
        raise DataFormatError(f"{where}: temperature_source must be 'freq' or 'probe', got {source!r}",
                              column="temperature_source")
    probe = _reference_probe(dataset, channel, opts, "probe")
    return {"kind": "probe", "column": pick_temperature_column(dataset, probe, where)}


def _temperature(dataset: Dataset, source: dict[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    if source["kind"] == "reverse_cubic":
        return _reverse_from_definition(source).evaluate_clipped(_column(dataset, source["freq_column"], where))
    T = _column(dataset, source["column"], where)
    return T, np.zeros(T.size, bool)


def _eq7_inputs(dataset: Dataset, channel: str, opts: dict[str, Any], where: str):
    source = _temperature_source(dataset, channel, opts, where)
    T, _ = _temperature(dataset, source, where)
    t = _column(dataset, "time_s", where)
    y = _column(dataset, f"gyro_{channel}", where)
    average_s = float(opts.get("average_s", 100.0))
    tb, cols, segb, _ = block_means(t, {"T": T, "y": y}, average_s, run_segments(t, dataset.columns.get("run")))
    rate = temperature_rate(tb, cols["T"], average_s, method=RATE_METHOD, segments=segb)
    validity = thermal_validity(dataset, T, average_s, cols["T"], rate)
    return source, cols["T"], rate, cols["y"], average_s, validity


def _eq7_result(model: str, channel: str, source: dict[str, Any], average_s: float, validity: dict[str, float],
                T: np.ndarray, rate: np.ndarray, y: np.ndarray, k: np.ndarray, extra_def: dict[str, Any],
                extra_stats: dict[str, Any]) -> FitResult:
    resid = y - eq7_design(T, rate) @ k
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return FitResult(
        model=model, channel=channel, target=f"gyro_{channel}",
        definition={"formula": "B = k0 + k1 T + k2 T^2 + k3 dT + k4 dT^2 + k5 T dT (T in C, dT = dT/dt in C/min)",
                    "source": "seed 002 eq 7", "temperature_source": source, "average_s": average_s,
                    "temperature_column": source.get("column"),
                    "rate_method": RATE_METHOD, "rate_window_s": average_s,
                    "rate_filter": f"Savitzky-Golay order 2 over {average_s:g} s (gradient on {average_s:g}-s means)",
                    **extra_def},
        coefficients={name: float(v) for name, v in zip(EQ7_TERMS, k)},
        units=dict(EQ7_UNITS),
        validity=dict(validity),
        stats={"n": int(y.size), "rms_dph": float(np.sqrt(np.mean(resid ** 2))),
               "r2": 1.0 - float(resid @ resid) / ss_tot if ss_tot > 0 else float("nan"), **extra_stats},
    )


def fit_hrg(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """Eq 7 by least squares.  Options: temperature_source ("freq" | "probe"), reverse (an hrg_reverse
    FitResult), reference/probe, average_s (100)."""
    where = f"hrg gyro_{channel}"
    source, T, rate, y, average_s, validity = _eq7_inputs(dataset, channel, opts, where)
    k, info = fit_eq7_ls(T, rate, y)
    return _eq7_result("hrg", channel, source, average_s, validity, T, rate, y, k, {"solver": "least squares"},
                       {"cost_ls": info["cost"], "cond": info["cond_raw"], "cond_standardised": info["cond_std"]})


def fit_hrg_pso(dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """Eq 7 by PSO (paper settings).  Extra options: seed (RNG, default 0), bound (3.0, standardised),
    seed_with_ls (True), compare_unseeded (True: also run without the LS particle and report its cost),
    n_particles/iterations/c1/c2/w."""
    where = f"hrg_pso gyro_{channel}"
    source, T, rate, y, average_s, validity = _eq7_inputs(dataset, channel, opts, where)
    settings = pso.PsoSettings(**{k: opts[k] for k in ("n_particles", "iterations", "c1", "c2", "w") if k in opts},
                               seed=opts.get("seed", 0))
    bound = float(opts.get("bound", 3.0))
    seeded = bool(opts.get("seed_with_ls", True))
    k, info = fit_eq7_pso(T, rate, y, settings=settings, bound=bound, seed_with_ls=seeded)
    stats = {"cost_pso": info["cost_pso"], "cost_ls": info["cost_ls"], "cost_ratio": info["cost_ratio"],
             "pso_seeded_with_ls": info["seeded"], "at_bound": info["at_bound"],
             "ls_outside_bounds": info["ls_outside_bounds"], "cond": info["cond_raw"],
             "cond_standardised": info["cond_std"],
             "note": "eq 7 is linear in k: least squares is the global optimum of eq 8; PSO can only match it"}
    if opts.get("compare_unseeded", True):
        _, other = fit_eq7_pso(T, rate, y, settings=settings, bound=bound, seed_with_ls=not seeded)
        stats["cost_pso_" + ("unseeded" if seeded else "seeded")] = other["cost_pso"]
    return _eq7_result("hrg_pso", channel, source, average_s, validity, T, rate, y, k,
                       {"solver": "PSO", "pso": {"n_particles": settings.n_particles, "iterations": settings.iterations,
                                                 "c1": settings.c1, "c2": settings.c2, "w": settings.w,
                                                 "bound_standardised": bound, "seed": settings.seed,
                                                 "seed_with_ls": seeded}}, stats)


def predict_hrg(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """Eq-7 bias at every sample (for "hrg" and "hrg_pso").  Flagged: frequency outside the reverse
    cubic's range, or T / dT/dt outside the fitted ranges (all clipped before evaluation)."""
    d = result.definition
    where = f"{result.model} prediction"
    T, flag_f = _temperature(dataset, d["temperature_source"], where)
    Ts, rate = per_sample_thermal(dataset, T, float(d["average_s"]))
    v = result.validity
    Tc = np.clip(Ts, v["tmin_c"], v["tmax_c"])
    rc = np.clip(rate, v["dtdt_min_c_per_min"], v["dtdt_max_c_per_min"])
    k = np.array([result.coefficients[n] for n in EQ7_TERMS])
    return apply_mode(eq7_design(Tc, rc) @ k, flag_f | (Tc != Ts) | (rc != rate), opts, where)


predict_hrg_pso = predict_hrg
