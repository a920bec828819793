"""Close the loop: fit the declared model, find what its residual still contains, trace it to a
physical effect, add it, and report the error before and after on a held-out run.

Method (calibration-notes sections 4 and 7):

1. Fit the declared model (a linear design: a formula or a named model expressed as one) on TRAIN,
   Earth rate removed when orientation and latitude are known.
2. For every candidate of ``bench.fit.effects`` (with its nonlinear parameter scanned), fit the
   declared design plus the candidate's columns on TRAIN.  Evidence is computed on 100-s block means
   (about one point per thermal time step, which removes the white noise and most of the
   autocorrelation) with two tests that survive the remaining autocorrelation: a Wald test with
   Newey-West (HAC) covariance of the new coefficients, and a BIC difference computed with the
   effective number of points n_eff = n (1 - rho) / (1 + rho) (rho = lag-1 autocorrelation of the
   block residual).  The nonlinear parameter search adds one parameter to the BIC penalty.
3. Significant candidates (HAC p < 1e-3 and delta-BIC > 10) are ranked by delta-BIC; the first one
   that also lowers the VALIDATE std of 100-s means by at least 5 % is added.  Repeat until none.
4. Noise floor: the Allan deviation of the TRAIN residual at tau = 100 s (for white noise it equals
   the std of 100-s means; slow structure barely moves it).  Structure remains when the validation
   std of 100-s means is well above that floor (> 1.5x) and a whiteness, spectral-peak or trend
   test on the 100-s means fails; it is described (period, amplitude, slope) instead of being
   "explained" with terms that do not help on VALIDATE.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.fit import effects as fx
from bench.fit.base import Dataset
from bench.fit.linear import newey_west_lags
from bench.fit.metrics import bias_stability, window_means

BLOCK_S = 100.0
P_MAX = 1e-3
DBIC_MIN = 10.0
MIN_VALIDATION_GAIN = 0.05
STRUCTURE_RATIO = 1.5
MAX_EFFECTS = 4
AMBIGUOUS_DBIC = 10.0       # a runner-up this close to the winner is reported as indistinguishable


@dataclass
class Design:
    names: list[str]
    train: np.ndarray      # (n_train, k)
    validate: np.ndarray   # (n_val, k)


# --------------------------------------------------------------------------------------------
# small numerical helpers

def block_means(x: np.ndarray, time_s: np.ndarray, block_s: float = BLOCK_S) -> np.ndarray:
    """Means over consecutive blocks of ``block_s`` seconds (last partial block dropped).  x may be 1-D
    or 2-D (rows = samples)."""
    dt = fx.sample_period(time_s)
    per = max(1, int(round(block_s / dt)))
    n = (len(x) // per) * per
    if n == 0:
        return x[:0]
    shaped = x[:n].reshape((n // per, per) + x.shape[1:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # an all-missing block is NaN, on purpose
        return np.nanmean(shaped, axis=1)


def std100(residual: np.ndarray, time_s: np.ndarray) -> float:
    """Bias stability: std of 100-s means (GJB 2426A convention), the fitting module's definition."""
    return bias_stability(time_s, residual, 100.0)


def rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def _finite_rows(X: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    ok = np.all(np.isfinite(X), axis=1) if X.ndim == 2 else np.isfinite(X)
    return ok & np.isfinite(y) if y is not None else ok


def lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares on column-scaled X (numerically safe for powers of temperature); rows with a
    missing value (gyro off, probe lost) are left out."""
    ok = _finite_rows(X, y)
    X, y = X[ok], y[ok]
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    scale[scale == 0] = 1.0
    beta, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    return beta / scale


def lag1(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    x = x - x.mean()
    den = float(np.dot(x, x))
    return float(np.dot(x[1:], x[:-1]) / den) if den > 0 else 0.0


def hac_wald_p(X: np.ndarray, y: np.ndarray, new_cols: list[int]) -> float:
    """p-value of the joint Wald test that the ``new_cols`` coefficients are 0, HAC covariance."""
    import statsmodels.api as sm

    ok = _finite_rows(X, y)
    X, y = X[ok], y[ok]
    n = len(y)
    maxlags = max(1, newey_west_lags(n))
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    scale[scale == 0] = 1.0
    res = sm.OLS(y, X / scale).fit(cov_type="HAC", cov_kwds={"maxlags": maxlags})
    R = np.zeros((len(new_cols), X.shape[1]))
    for i, c in enumerate(new_cols):
        R[i, c] = 1.0
    try:
        test = res.wald_test(R, scalar=True)
        return float(test.pvalue)
    except (np.linalg.LinAlgError, ValueError):
        return 1.0


def allan_at(residual: np.ndarray, time_s: np.ndarray, tau_s: float) -> float:
    import allantools

    x = residual[np.isfinite(residual)]
    rate = 1.0 / fx.sample_period(time_s)
    taus, adev, _, _ = allantools.oadev(x, rate=rate, data_type="freq", taus=np.array([tau_s]))
    return float(adev[0]) if len(adev) else float("nan")


# --------------------------------------------------------------------------------------------
# structure tests on what is left

def describe_structure(residual: np.ndarray, time_s: np.ndarray, noise_floor: float) -> dict[str, Any]:
    """Tests the 100-s means of a residual for leftover structure: whiteness (Ljung-Box), the
    strongest periodic component (Fisher's g test on the periodogram) and a linear trend (HAC)."""
    import statsmodels.api as sm
    from statsmodels.stats.diagnostic import acorr_ljungbox

    means = window_means(time_s, residual, 100.0)
    n = len(means)
    out: dict[str, Any] = {"n_blocks": int(n)}
    if n < 12:
        out["testable"] = False
        return out
    out["testable"] = True
    centred = means - means.mean()
    s = float(np.std(means, ddof=1))
    out["std100_dph"] = s
    out["ratio_to_noise_floor"] = s / noise_floor if noise_floor > 0 else float("inf")
    lb = acorr_ljungbox(centred, lags=[min(10, n // 5)], return_df=True)
    out["ljung_box_p"] = float(lb["lb_pvalue"].iloc[0])
    # periodogram and Fisher's g; the peak frequency is then refined by least squares
    spec = np.abs(np.fft.rfft(centred)) ** 2
    spec = spec[1:]
    if len(spec) > 2:
        k = int(np.argmax(spec))
        g = spec[k] / spec.sum()
        m = len(spec)
        # P(g > x) ~ m (1 - x)^(m-1) (first term of Fisher's exact formula)
        out["peak_p"] = float(min(1.0, m * (1 - g) ** (m - 1)))
        tt = np.arange(n) * 100.0

        def sine_fit(freq: float) -> tuple[float, float]:
            basis = np.column_stack([np.cos(2 * np.pi * freq * tt), np.sin(2 * np.pi * freq * tt)])
            coef, *_ = np.linalg.lstsq(basis, centred, rcond=None)
            return float(np.sum((centred - basis @ coef) ** 2)), float(np.hypot(*coef))

        from scipy.optimize import minimize_scalar
        df = 1.0 / (n * 100.0)
        f0 = (k + 1) * df
        best = minimize_scalar(lambda f: sine_fit(f)[0], bounds=(max(f0 - df, df / 4), f0 + df), method="bounded")
        out["peak_period_s"] = float(1.0 / best.x)
        out["peak_amplitude_dph"] = sine_fit(best.x)[1]
    tt_h = np.arange(n) * 100.0 / 3600.0
    X = sm.add_constant(tt_h)
    maxlags = max(1, newey_west_lags(n))
    res = sm.OLS(means, X).fit(cov_type="HAC", cov_kwds={"maxlags": maxlags})
    out["trend_dph_per_h"] = float(res.params[1])
    out["trend_p"] = float(res.pvalues[1])
    failed = [name for name, key in (("whiteness", "ljung_box_p"), ("periodic", "peak_p"), ("trend", "trend_p"))
              if out.get(key, 1.0) < 0.01]
    out["failed_tests"] = failed
    out["structure"] = bool(failed) and out["ratio_to_noise_floor"] > STRUCTURE_RATIO
    return out


# --------------------------------------------------------------------------------------------
# the loop

def close_loop_channel(design: Design, y_train: np.ndarray, y_val: np.ndarray, train: Dataset,
                       validate: Dataset, ctx: fx.Context, declared_name: str) -> dict[str, Any]:
    t_tr, t_va = train.time, validate.time
    names = list(design.names)
    X_tr, X_va = design.train, design.validate
    beta = lstsq(X_tr, y_train)
    r_tr, r_va = y_train - X_tr @ beta, y_val - X_va @ beta
    before = _errors(r_tr, r_va, t_tr, t_va)

    library = fx.candidates(ctx, train)
    built: dict[str, tuple[dict, dict]] = {}
    added: list[dict[str, Any]] = []
    used_kinds: set[str] = set()
    y_tr_blocks = block_means(y_train, t_tr)
    current_val_std = before["validation_std100_dph"]

    for _ in range(MAX_EFFECTS):
        Xb = block_means(X_tr, t_tr)
        base_res = y_tr_blocks - Xb @ lstsq(Xb, y_tr_blocks)
        ssr0 = float(np.nansum(base_res ** 2))
        rho = min(max(lag1(base_res), 0.0), 0.95)
        n = int(np.isfinite(base_res).sum())
        n_eff = max(10.0, n * (1 - rho) / (1 + rho))
        best_by_kind: dict[str, dict[str, Any]] = {}
        for cand in library:
            if cand.kind in used_kinds and cand.kind not in ("gradient",):
                continue
            key = cand.label
            if key not in built:
                built[key] = (cand.build(train), cand.build(validate))
            scored = _score(cand, built[key][0], X_tr, Xb, y_tr_blocks, t_tr, ssr0, n_eff)
            if scored is None:
                continue
            prev = best_by_kind.get(cand.kind)
            if prev is None or scored["dbic"] > prev["dbic"]:
                best_by_kind[cand.kind] = scored
        for kind, entry in best_by_kind.items():
            if entry["cand"].at_tau is not None:
                best_by_kind[kind] = _refine_tau(entry, X_tr, Xb, y_tr_blocks, t_tr, ssr0, n_eff, train, validate, built)
        ranked = sorted(best_by_kind.values(), key=lambda e: -e["dbic"])
        chosen = None
        for entry in ranked:
            if entry["dbic"] < DBIC_MIN:
                break
            cand = entry["cand"]
            cols_tr, cols_va = built[cand.label]
            Xa_tr = np.column_stack([X_tr] + list(cols_tr.values()))
            Xa_va = np.column_stack([X_va] + list(cols_va.values()))
            p = hac_wald_p(block_means(Xa_tr, t_tr), y_tr_blocks, entry["new_cols"])
            entry["hac_p"] = p
            if p >= P_MAX:
                continue
            b = lstsq(Xa_tr, y_train)
            val_std = std100(y_val - Xa_va @ b, t_va)
            entry["validation_std100_dph"] = val_std
            if val_std < current_val_std * (1 - MIN_VALIDATION_GAIN):
                chosen = (entry, Xa_tr, Xa_va, b, cols_tr)
                break
        if chosen is None:
            break
        entry, X_tr, X_va, beta, cols_tr = chosen
        cand = entry["cand"]
        new_names = list(cols_tr.keys())
        names.extend(new_names)
        used_kinds.add(cand.kind)
        current_val_std = entry["validation_std100_dph"]
        added.append({
            "kind": cand.kind,
            "params": dict(cand.params),
            "terms": new_names,
            "coefficients": {nm: float(beta[len(names) - len(new_names) + i]) for i, nm in enumerate(new_names)},
            "evidence": {"delta_bic": entry["dbic"], "hac_wald_p": entry["hac_p"], "n_blocks": n,
                         "n_eff": float(n_eff), "block_s": BLOCK_S,
                         "runner_up": _runner_up(ranked, cand.kind)},
            "validation_std100_dph": current_val_std,
        })

    beta = lstsq(X_tr, y_train)
    r_tr, r_va = y_train - X_tr @ beta, y_val - X_va @ beta
    after = _errors(r_tr, r_va, t_tr, t_va)
    noise_floor = allan_at(r_tr, t_tr, 100.0)
    structure = {"train": describe_structure(r_tr, t_tr, noise_floor),
                 "validation": describe_structure(r_va, t_va, noise_floor)}
    remains = structure["validation"].get("structure", False) or structure["train"].get("structure", False)
    if remains:
        verdict = "unexplained_structure_remains"
    elif added:
        verdict = "explained"
    else:
        verdict = "no_effect_missing"
    return {
        "declared_model": declared_name,
        "declared_terms": list(design.names),
        "primary_probe": ctx.primary_probe,
        "rate_window_s": ctx.rate_window_s,
        "noise_floor_dph": noise_floor,
        "before": before,
        "after": after,
        "effects_added": added,
        "final_terms": names,
        "final_coefficients": {nm: float(b) for nm, b in zip(names, beta)},
        "structure": structure,
        "verdict": verdict,
        "findings": _findings(declared_name, before, after, added, structure, verdict, noise_floor),
        "_residuals": {"before": (y_train - design.train @ lstsq(design.train, y_train),
                                  y_val - design.validate @ lstsq(design.train, y_train)),
                       "after": (r_tr, r_va)},
    }


def _score(cand, cols_tr, X_tr, Xb, y_blocks, t_tr, ssr0, n_eff) -> dict[str, Any] | None:
    """Delta-BIC of adding the candidate's columns to the current design (100-s block means)."""
    Z_tr = np.column_stack(list(cols_tr.values()))
    Xab = block_means(np.column_stack([X_tr, Z_tr]), t_tr)
    rank_gain = _rank(Xab) - _rank(Xb)
    if rank_gain <= 0:
        return None
    ssr1 = float(np.nansum((y_blocks - Xab @ lstsq(Xab, y_blocks)) ** 2))
    if ssr1 <= 0 or ssr1 >= ssr0:
        return None
    dbic = n_eff * np.log(ssr0 / ssr1) - (rank_gain + cand.n_nonlinear) * np.log(n_eff)
    return {"cand": cand, "dbic": float(dbic), "ssr1": ssr1,
            "new_cols": list(range(X_tr.shape[1], X_tr.shape[1] + Z_tr.shape[1]))}


def _rank(x: np.ndarray) -> int:
    x = x[_finite_rows(x)]
    scale = np.sqrt(np.mean(x ** 2, axis=0))
    return int(np.linalg.matrix_rank(x / np.where(scale > 0, scale, 1.0)))


def _refine_tau(entry, X_tr, Xb, y_blocks, t_tr, ssr0, n_eff, train, validate, built):
    """Golden-section refinement of a searched time constant between its grid neighbours."""
    from scipy.optimize import minimize_scalar

    tau0 = float(entry["cand"].params["tau_s"])
    make = entry["cand"].at_tau

    def cost(log_tau: float) -> float:
        cand = make(float(np.exp(log_tau)))
        scored = _score(cand, cand.build(train), X_tr, Xb, y_blocks, t_tr, ssr0, n_eff)
        return -scored["dbic"] if scored else np.inf

    res = minimize_scalar(cost, bounds=(np.log(tau0 / 2.2), np.log(tau0 * 2.2)), method="bounded",
                          options={"xatol": 0.02})
    if not np.isfinite(res.fun) or -res.fun <= entry["dbic"]:
        return entry
    cand = make(float(np.exp(res.x)))
    built[cand.label] = (cand.build(train), cand.build(validate))
    return _score(cand, built[cand.label][0], X_tr, Xb, y_blocks, t_tr, ssr0, n_eff)


def _runner_up(ranked: list[dict[str, Any]], chosen_kind: str) -> dict[str, Any] | None:
    for e in ranked:
        if e["cand"].kind != chosen_kind:
            return {"kind": e["cand"].kind, "params": dict(e["cand"].params), "delta_bic": e["dbic"]}
    return None


def _errors(r_tr, r_va, t_tr, t_va) -> dict[str, float]:
    return {"train_rms_dph": rms(r_tr), "train_std100_dph": std100(r_tr, t_tr),
            "validation_rms_dph": rms(r_va), "validation_std100_dph": std100(r_va, t_va)}


def _findings(declared, before, after, added, structure, verdict, floor) -> str:
    lines = [f"Declared model {declared}: validation std of 100-s means "
             f"{before['validation_std100_dph']:.4g} deg/h before, {after['validation_std100_dph']:.4g} deg/h after; "
             f"noise floor (Allan deviation at 100 s) {floor:.4g} deg/h."]
    if not added:
        lines.append("No candidate effect was both significant on the training run and helpful on the "
                     "validation run; nothing was added.")
    for i, e in enumerate(added, 1):
        params = ", ".join(f"{k}={v}" for k, v in e["params"].items())
        lines.append(f"{i}. Added {e['kind']}" + (f" ({params})" if params else "") +
                     f": delta-BIC {e['evidence']['delta_bic']:.1f}, HAC Wald p {e['evidence']['hac_wald_p']:.2g}; "
                     f"validation std100 now {e['validation_std100_dph']:.4g} deg/h.")
        runner = e["evidence"].get("runner_up")
        if runner and e["evidence"]["delta_bic"] - runner["delta_bic"] < AMBIGUOUS_DBIC:
            lines.append(f"   {runner['kind']} explains this residual almost as well (delta-BIC "
                         f"{runner['delta_bic']:.1f}): this data cannot tell the two apart; a run with a "
                         f"different ramp pattern would.")
    st = structure["validation"] if structure["validation"].get("testable") else structure["train"]
    if verdict == "unexplained_structure_remains":
        parts = []
        if "periodic" in st.get("failed_tests", []):
            parts.append(f"a periodic component of period {st['peak_period_s'] / 3600:.2f} h and amplitude "
                         f"{st['peak_amplitude_dph']:.3g} deg/h")
        if "trend" in st.get("failed_tests", []):
            parts.append(f"a trend of {st['trend_dph_per_h']:.3g} deg/h per hour")
        if "whiteness" in st.get("failed_tests", []):
            parts.append(f"correlated 100-s means (Ljung-Box p {st['ljung_box_p']:.2g})")
        lines.append("Structure remains that no candidate explains: " + "; ".join(parts) +
                     f". The validation std100 is {st['ratio_to_noise_floor']:.2f}x the noise floor. "
                     "No terms were added for it because none helped on the validation run.")
    elif verdict == "explained":
        lines.append("What is left is consistent with the noise floor "
                     f"({st.get('ratio_to_noise_floor', float('nan')):.2f}x).")
    else:
        lines.append("The declared model is complete for this data: the residual is at the noise floor "
                     f"({st.get('ratio_to_noise_floor', float('nan')):.2f}x).")
    return " ".join(lines)


# --------------------------------------------------------------------------------------------
# entry point

def _declared_design(model: str, train: Dataset, validate: Dataset, channel: str,
                     latitude_deg: float | None, opts: dict[str, Any]):
    """Fit the declared model once with the fitting module (to get its exact term list), then build
    its design matrix on both runs.  Only models linear in their coefficients can be extended."""
    from bench.fit.formula import compiled_from_recipe
    from bench.fit.models import fit_model, prepare_fit_data

    declared = fit_model(model, train, channel, latitude_deg=latitude_deg, **opts)
    d = declared.definition
    if d.get("kind") != "linear":
        raise ValueError(f"close-loop extends models that are linear in their coefficients; {model!r} is "
                         f"{d.get('kind', 'not linear')} — use static, dynamic, patent37, hrg or a formula")
    window = d["rate_filter"]["window_s"]
    compiled = compiled_from_recipe(d["terms"], d.get("formula", ""), window)
    out = []
    for ds, clip in ((train, None), (validate, declared.validity.get("signals"))):
        work, y, _ = prepare_fit_data(ds, channel, latitude_deg=latitude_deg, rate_window_s=window)
        if "table_rate_dps" in ds:
            # the table's rate is a true input along the channel under test (rate tests align them)
            y = y - np.nan_to_num(np.asarray(ds["table_rate_dps"], dtype=float)) * 3600.0
        # on the held-out run the declared model's inputs are clipped to the training ranges, as the
        # stored model would be applied (never a silent extrapolation)
        x, _ = compiled.design(work, clip=clip)
        out.append((x, y))
    (x_tr, y_tr), (x_va, y_va) = out
    probe = d.get("probe") or _first_probe(compiled, train)
    return declared, Design(list(compiled.names), x_tr, x_va), y_tr, y_va, probe, window


def _first_probe(compiled, ds: Dataset) -> str:
    for node in compiled.signal_nodes().values():
        col = node.get("column", "")
        if col.startswith("temp_"):
            return col[len("temp_"):]
    names = ds.temp_names()
    if not names:
        raise ValueError("close-loop needs at least one temp_<name> column")
    return names[0]


def close_loop(train: Dataset, validate: Dataset, model: str, *, channels: list[str] | None = None,
               latitude_deg: float | None = None, **fit_opts: Any) -> dict[str, Any]:
    """Run the close-loop analysis for each channel; returns the JSON-ready report (residual arrays
    for plotting are kept under the private key ``_residuals`` of each channel)."""
    channels = channels or train.gyro_channels()
    if latitude_deg is None and "latitude_deg" in train.meta:
        latitude_deg = float(train.meta["latitude_deg"])
    report: dict[str, Any] = {"model": model, "latitude_deg": latitude_deg, "block_s": BLOCK_S,
                              "thresholds": {"hac_p_max": P_MAX, "delta_bic_min": DBIC_MIN,
                                             "min_validation_gain": MIN_VALIDATION_GAIN,
                                             "structure_ratio": STRUCTURE_RATIO},
                              "channels": {}}
    for ch in channels:
        missing = [f"gyro_{ch}" for ds in (train, validate) if f"gyro_{ch}" not in ds]
        if missing:
            raise ValueError(f"channel {ch!r}: column gyro_{ch} missing from the "
                             f"{'training' if f'gyro_{ch}' not in train else 'validation'} data")
        declared, design, y_tr, y_va, probe, window = _declared_design(model, train, validate, ch, latitude_deg, fit_opts)
        ctx = fx.Context(channel=ch, primary_probe=probe, probes=tuple(train.temp_names()),
                         channels=tuple(train.gyro_channels()), latitude_deg=latitude_deg, rate_window_s=window)
        report["channels"][ch] = close_loop_channel(design, y_tr, y_va, train, validate, ctx, model)
    return report


def public(report: dict[str, Any]) -> dict[str, Any]:
    """The report without the private residual arrays (what goes into the JSON file)."""
    return {**report, "channels": {ch: {k: v for k, v in r.items() if not k.startswith("_")}
                                   for ch, r in report["channels"].items()}}
