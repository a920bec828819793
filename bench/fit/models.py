"""Bias models, the model registry, and evaluation on new data (predict / apply).

Linear models (all fitted by ``bench.fit.linear.lstsq`` through the formula engine, so every one of
them exports the same term-list evaluation recipe):

* ``static``   S000 eq 3: bias = A0 + A1 d + A2 d^2 + A3 d^3, d = T_probe - t0 (t0 = 25 C).  Default
  weighting: 0.5 C temperature bins (calibration-notes lesson 1); ``bin_c=None`` fits every sample.
* ``dynamic``  S000 eq 4 / eq 5: bias = B0 + sum_j k_j (T - t0)^j + sum_j p_j (T_a - T_b)^j
  + sum_j q_j (dT/dt)^j with orders ``l, m, n`` (default 1, 1, 1 = eq 4; names k, p, q when the order
  is 1, else k1..kl, p1..pm, q1..qn).  ``t0_c`` is a fixed number (default 25 C) or ``"power_on"`` =
  the first valid probe temperature of the fit data (S000: "初值"), stored as a number.
* ``patent37`` S001: a0 + for each of 4 probes: T, T^2, T^3, r, r^2, r^3, T r, (T r)^2, (T r)^3 with
  T centred (T - t0, t0 = 25 C) and r = dT/dt in C/min; coefficients a0..a36 in the patent order.
  The columns are equilibrated in the solver and the condition number is reported in ``stats.cond``.
* ``formula``  an intercept plus user terms (see ``bench.fit.formula``); any string that is not a
  registered model name is parsed as a formula.

The channel's own probe: ``static`` and ``dynamic`` are built on it, ``patent37`` records it (and spans
its hull with it) when it is one of its four probes, and a formula's ``tc``/``dtc`` stand for it.  It is
the ``probe=`` option when given, else ``bench.fit.base.channel_probe`` (the data's
``meta["channel_probes"]``, else the default); ``definition["probe"]`` records it and
``definition["probe_source"]`` where it came from.

Common options of the linear models (``fit_model(name, ds, channel, **opts)``):
``earth_rate`` (None = remove when latitude and the channel's axis are known, True = must remove,
False = keep), ``latitude_deg``, ``axis`` (body vector of the channel), ``rate_window_s`` (dT/dt
filter, default 120 s), ``average_s`` (block-average before fitting, e.g. 100), ``pauta`` (3-sigma
rejection on the residual, refit; default True), ``bin_c`` (temperature bins; static default 0.5).

Validity (lesson 2): ``validity = {"tmin_c", "tmax_c", "signals": {key: [lo, hi]}, "hull": [[T, dT/dt],
...], "hull_signals": [kT, kR]}`` from the fit data.  ``predict(result, ds, mode="clip")`` clips every
input signal to its fitted range (PX4 TMIN/TMAX style) and returns ``flagged`` = outside a range or
outside the (T, dT/dt) hull; ``mode="nan"`` also sets flagged predictions to NaN.  Never a silent
extrapolation.

Registry (for the HRG/FOG helper)::

    register_model(name, fit_fn, predict_fn, *, description="", replace=False)
        fit_fn(dataset, channel, **opts) -> FitResult ; predict_fn(result, dataset, **opts) -> (values, flagged)
    registered_models() -> dict[name, description]
    fit_model(name_or_formula, dataset, channel, **opts) -> FitResult
    predict(result, dataset, **opts) -> (values, flagged)
    compensate(result, dataset, **opts) -> (gyro minus predicted bias, flagged)

Reusable building blocks: ``prepare_fit_data``, ``fit_linear_terms``, ``linear_validity``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from bench.errors import DataFormatError
from bench.fit import prep
from bench.fit.base import EARTH_RATE_DPH, Dataset, FitResult, channel_probe, channel_probe_map
from bench.fit.formula import (CompiledFormula, compile_formula, compile_terms, compiled_from_recipe,
                               signal_key, uses_channel_probe)
from bench.fit.linear import lstsq
from bench.fit.metrics import bias_stability

FitFn = Callable[..., FitResult]
PredictFn = Callable[..., tuple[np.ndarray, np.ndarray]]
RATE_METHOD = "centred_slope"   # bench.signal.temperature_rate method of every dT/dt term here
RATE_FILTER_TEXT = ("centred least-squares slope of the temperature over window_s seconds (Savitzky-Golay "
                    "first derivative), in C/min")


NeedsFn = Callable[[str, dict[str, Any]], list[str]]


def _needs_gyro(channel: str, opts: dict[str, Any]) -> list[str]:
    return [f"gyro_{channel}"]


@dataclass(frozen=True)
class ModelSpec:
    name: str
    fit: FitFn
    predict: PredictFn
    description: str = ""
    needs: NeedsFn = _needs_gyro       # (channel, options) -> columns the fit cannot do without


_REGISTRY: dict[str, ModelSpec] = {}


def register_model(name: str, fit_fn: FitFn, predict_fn: PredictFn, *, description: str = "",
                   replace: bool = False, needs: NeedsFn | None = None) -> None:
    """Add a model to the registry (``fit_fn(ds, channel, **opts)``, ``predict_fn(result, ds, **opts)``;
    ``needs(channel, opts)``: the columns it needs, checked before fitting; default ``gyro_<channel>``)."""
    if not name.isidentifier():
        raise ValueError(f"model name {name!r} must be an identifier")
    if name in _REGISTRY and not replace:
        raise ValueError(f"model {name!r} already registered")
    _REGISTRY[name] = ModelSpec(name, fit_fn, predict_fn, description, needs or _needs_gyro)


def required_columns(name: str, channel: str, opts: dict[str, Any] | None = None) -> list[str]:
    """The columns model ``name`` needs to fit ``channel`` with ``opts`` (a formula: ``gyro_<channel>``)."""
    spec = _REGISTRY.get(name.strip())
    return (spec.needs if spec is not None else _needs_gyro)(channel, dict(opts or {}))


def check_columns(name: str, dataset: Dataset, channel: str, opts: dict[str, Any] | None = None) -> None:
    """Refuse a dataset that lacks a column the model needs, naming it and the columns present."""
    missing = [c for c in required_columns(name, channel, opts) if c not in dataset]
    if missing:
        raise DataFormatError(f"{name.strip()} on channel {channel}: no {', '.join(missing)} in data, which the "
                              f"model needs (columns present: {', '.join(dataset.columns)})", column=missing[0])


def registered_models() -> dict[str, str]:
    return {k: v.description for k, v in _REGISTRY.items()}


def fit_model(name_or_formula: str, dataset: Dataset, channel: str, **opts: Any) -> FitResult:
    """Fit a registered model by name, or a formula (any other text) to ``gyro_<channel>``."""
    spec = _REGISTRY.get(name_or_formula.strip())
    if spec is not None:
        check_columns(spec.name, dataset, channel, opts)
        return spec.fit(dataset, channel, **opts)
    return fit_formula(dataset, channel, formula=name_or_formula, **opts)


def predict(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """Predicted bias (deg/h) of ``result`` on ``dataset`` and the boolean ``flagged`` array."""
    spec = _REGISTRY.get(result.model)
    if spec is None:
        raise DataFormatError(f"model {result.model!r} is not registered (have: {', '.join(_REGISTRY)})")
    return spec.predict(result, dataset, **opts)


def compensate(result: FitResult, dataset: Dataset, **opts: Any) -> tuple[np.ndarray, np.ndarray]:
    """``gyro_<channel>`` minus the predicted bias, and ``flagged``."""
    values, flagged = predict(result, dataset, **opts)
    return np.asarray(dataset[result.target], dtype=np.float64) - values, flagged


# ------------------------------------------------------------------------------------ preparation
def _resolve_channel(ds: Dataset, channel: str) -> str:
    if f"gyro_{channel}" not in ds:
        raise DataFormatError(f"no gyro_{channel} in data (channels: {', '.join(ds.gyro_channels()) or 'none'})")
    return f"gyro_{channel}"


def prepare_fit_data(ds: Dataset, channel: str, *, earth_rate: bool | None = None,
                     latitude_deg: float | None = None, axis: Any = None,
                     rate_window_s: float = prep.DEFAULT_RATE_WINDOW_S, average_s: float | None = None,
                     ) -> tuple[Dataset, np.ndarray, dict[str, Any]]:
    """Target ``gyro_<channel>`` with the Earth rate handled, ``rate_<probe>`` columns added (computed
    on the full-rate data, before any averaging), optional block averaging.  Returns (dataset, y, info)."""
    target = _resolve_channel(ds, channel)
    y = np.asarray(ds[target], dtype=np.float64)
    info: dict[str, Any] = {"target": target, "earth_rate_removed": False}
    already = ds.meta.get("earth_rate_removed") == "yes"
    lat_known = latitude_deg is not None or "latitude_deg" in ds.meta
    axis_known = axis is not None or channel in ("x", "y", "z")
    if already:
        info["earth_rate_removed"] = "before fit (dataset meta)"
    elif earth_rate or (earth_rate is None and lat_known and axis_known):
        er = prep.earth_rate_reading(ds, channel, latitude_deg, axis)
        y = y - er
        info["earth_rate_removed"] = True
        info["latitude_deg"] = float(latitude_deg if latitude_deg is not None else ds.meta["latitude_deg"])
        info["axis"] = (prep.default_axis(channel) if axis is None else np.asarray(axis, float)).tolist()
        if "orientation" in ds:
            unknown = np.asarray(ds["orientation"]).astype(str) == ""
            if unknown.any():       # the Earth rate there is unknown: leave those rows out, say so
                y = np.where(unknown, np.nan, y)
                info["warning"] = (f"{int(unknown.sum())} of {unknown.size} rows have no orientation: their Earth "
                                   f"rate is unknown, so they are left out of the fit")
    elif not lat_known and axis_known and "orientation" in ds and \
            bool((np.asarray(ds["orientation"]).astype(str) != "").any()):
        info["warning"] = (f"latitude unknown: the Earth rate (up to {EARTH_RATE_DPH:.2f} deg/h on {target}) stays in "
                           f"the fitted bias (intercept); give latitude_deg (CSV '# latitude_deg: ...' or --latitude)")
    work = prep.add_rates(ds, rate_window_s)
    work = work.with_columns(**{"__target": y})
    if average_s:
        work = prep.block_average(work, float(average_s))
        info["average_s"] = float(average_s)
    return work, np.asarray(work["__target"]), info


def _hull(points: np.ndarray) -> tuple[list[list[float]], np.ndarray | None, np.ndarray | None]:
    """Convex hull of (T, rate) points: (vertices, equations in scaled coords, scale [centre, span])."""
    pts = points[np.all(np.isfinite(points), axis=1)]
    if len(pts) < 3:
        return [], None, None
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    scaled = (pts - lo) / span
    try:
        h = ConvexHull(scaled)
    except QhullError:
        try:
            h = ConvexHull(np.unique(np.round(scaled, 9), axis=0))
        except QhullError:       # degenerate (e.g. a constant rate): no hull, box limits still apply
            return [], None, None
    verts = h.points[h.vertices] * span + lo
    return verts.tolist(), h.equations, np.vstack([lo, span])


def inside_hull(vertices: list[list[float]], points: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """True where (T, rate) points lie inside the convex hull with ``vertices`` (scaled tolerance)."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    h = ConvexHull((v - lo) / span)
    p = (np.asarray(points, dtype=np.float64) - lo) / span
    d = p @ h.equations[:, :2].T + h.equations[:, 2]
    return np.all(d <= tol, axis=1)


def linear_validity(compiled: CompiledFormula, ds: Dataset, signals: dict[str, np.ndarray],
                    used: np.ndarray, probe: str | None) -> dict[str, Any]:
    ranges = {k: [float(np.nanmin(v[used])), float(np.nanmax(v[used]))] for k, v in signals.items()}
    temps = [r for k, r in ranges.items() if k.startswith("temp:")]
    validity: dict[str, Any] = {"signals": ranges, "outside": "clip to range, flagged"}
    if temps:
        validity["tmin_c"] = min(r[0] for r in temps)
        validity["tmax_c"] = max(r[1] for r in temps)
    if probe is not None:
        kt, kr = f"temp:temp_{probe}", f"rate:temp_{probe}"
        if kt in signals and kr in signals:
            pts = np.column_stack([signals[kt][used], signals[kr][used]])
            verts, _eq, _sc = _hull(pts)
            if verts:
                validity["hull"] = verts
                validity["hull_signals"] = [kt, kr]
    return validity


def fit_linear_terms(model: str, ds: Dataset, channel: str, *, terms: list[tuple[str, str]] | None = None,
                     formula: str | None = None, intercept: str = "intercept", probe: str | None = None,
                     extra_definition: dict[str, Any] | None = None, pauta: bool = True,
                     bin_c: float | None = None, earth_rate: bool | None = None,
                     latitude_deg: float | None = None, axis: Any = None,
                     rate_window_s: float = prep.DEFAULT_RATE_WINDOW_S, average_s: float | None = None,
                     ) -> FitResult:
    """Fit a model that is linear in its coefficients: named ``terms`` [(coef, expr)] or a ``formula``."""
    work, y, info = prepare_fit_data(ds, channel, earth_rate=earth_rate, latitude_deg=latitude_deg, axis=axis,
                                     rate_window_s=rate_window_s, average_s=average_s)
    columns = list(work.columns)
    if formula is not None:
        compiled = compile_formula(formula, columns, rate_window_s=rate_window_s, channel_probe=probe)
    else:
        compiled = compile_terms(terms or [], columns, rate_window_s=rate_window_s, intercept=intercept,
                                 channel_probe=probe)
    signals = compiled.signals(work)
    x, _ = compiled.design(work, signals=signals)
    keep = np.isfinite(y) & np.all(np.isfinite(x), axis=1)
    n_usable = int(keep.sum())
    n_rejected = 0
    weighting = "every sample" if not average_s else f"{average_s:g} s block means"
    for _ in range(3 if pauta else 1):
        if bin_c:
            if probe is None:
                raise DataFormatError(f"{model}: bin_c needs a probe")
            sub = work.select(keep)
            binned = prep.bin_dataset_by_temperature(sub, probe, bin_c)
            bx, _ = compiled.design(binned)
            weighting = f"temperature bins of {bin_c:g} C on temp_{probe} (equal weight per bin)"
            fit = lstsq(bx, np.asarray(binned["__target"]), names=compiled.names)
        else:
            fit = lstsq(x, np.where(keep, y, np.nan), names=compiled.names)
        resid = y - x @ fit.coef
        if not pauta:
            break
        new_keep = keep & prep.pauta_mask(np.where(keep, resid, np.nan))
        n_rejected = n_usable - int(new_keep.sum())
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    coef = dict(zip(compiled.names, (float(c) for c in fit.coef)))
    used = keep & np.isfinite(resid)
    # validity from every sample with finite inputs (Pauta rejects gyro outliers, not temperatures)
    validity = linear_validity(compiled, work, signals, np.all(np.isfinite(x), axis=1), probe)
    r_used = np.where(used, resid, np.nan)
    raw = np.where(used, y - np.nanmean(y[used]), np.nan)
    std_before = bias_stability(work.time, raw, 100.0)
    std_after = bias_stability(work.time, r_used, 100.0)
    stats = {**fit.stats(), "n": int(used.sum()), "n_fit_points": fit.n, "n_rejected": n_rejected,
             "rms_dph": float(np.sqrt(np.nanmean(r_used ** 2))), "std100_dph": std_after,
             "std100_before_dph": std_before,
             "improvement_pct": (100.0 * (std_before - std_after) / std_before) if std_before else float("nan"),
             "weighting": weighting, "pauta": bool(pauta)}
    definition = {
        "kind": "linear", "formula": compiled.text, "target": info["target"], "target_unit": "deg/h",
        "intercept": compiled.names[0], "terms": compiled.recipe(),
        "rate_method": RATE_METHOD, "rate_window_s": float(rate_window_s),
        "rate_filter": {"method": RATE_FILTER_TEXT, "window_s": float(rate_window_s), "unit": "C/min"},
        "earth_rate": {k: v for k, v in info.items() if k != "target"},
        "output": "bias_dph = sum over terms of coefficient * term value (intercept term = 1)",
        "compensated": f"{info['target']} - bias_dph (the Earth rate is a true input and stays in the output)",
    }
    if probe is not None:
        definition["probe"] = probe
    definition.update(extra_definition or {})
    return FitResult(model=model, channel=channel, target=info["target"], definition=definition,
                     coefficients=coef, units=dict(compiled.units), validity=validity, stats=stats)


def predict_linear(result: FitResult, ds: Dataset, *, mode: str = "clip") -> tuple[np.ndarray, np.ndarray]:
    """Evaluate a linear FitResult on ``ds``: inputs clipped to the fitted ranges, flagged returned."""
    if mode not in ("clip", "nan"):
        raise ValueError("predict mode must be 'clip' or 'nan'")
    d = result.definition
    compiled = compiled_from_recipe(d["terms"], d.get("formula", ""), d["rate_filter"]["window_s"],
                                    d.get("target_unit", "deg/h"))
    missing = [n.get("column") for n in compiled.signal_nodes().values() if n["column"] not in ds]
    if missing:
        raise DataFormatError(f"model {result.model!r} needs column(s) {', '.join(missing)} not in the data")
    signals = compiled.signals(ds)
    x, flagged = compiled.design(ds, clip=result.validity.get("signals"), signals=signals)
    values = x @ np.array([result.coefficients[n] for n in compiled.names])
    hull = result.validity.get("hull")
    if hull:
        kt, kr = result.validity["hull_signals"]
        pts = np.column_stack([signals[kt], signals[kr]])
        finite = np.all(np.isfinite(pts), axis=1)
        inside = np.ones(len(ds), dtype=bool)
        inside[finite] = inside_hull(hull, pts[finite])
        flagged |= ~inside
    if mode == "nan":
        values = np.where(flagged, np.nan, values)
    return values, flagged


# ------------------------------------------------------------------------------------- the models
def _own_probe(ds: Dataset, channel: str, probe: str | None) -> tuple[str, str]:
    """(probe, where it came from): the ``probe=`` option, else the channel's own probe
    (``bench.fit.base.channel_probe``: the data's ``channel_probes`` map, else the default)."""
    if probe:
        return _check_probe(ds, probe), "probe option"
    mapped = channel in channel_probe_map(ds)
    return channel_probe(ds, channel), "channel_probes metadata" if mapped else "default (no channel_probes entry)"


def _probe_needs(channel: str, opts: dict[str, Any]) -> list[str]:
    probe = opts.get("probe")
    if probe:
        return [f"gyro_{channel}", f"temp_{probe}"]
    return [f"gyro_{channel}"]           # the default probe is resolved (and refused) by base.default_probe


def _patent37_needs(channel: str, opts: dict[str, Any]) -> list[str]:
    probes = opts.get("probes") or ["t1", "t2", "t3", "t4"]
    return [f"gyro_{channel}"] + [f"temp_{p}" for p in probes]


def _check_probe(ds: Dataset, probe: str) -> str:
    if f"temp_{probe}" not in ds:
        raise DataFormatError(f"no temp_{probe} in data (probes: {', '.join(ds.temp_names())})")
    return probe


def _num(v: float) -> str:
    return repr(float(v))


def _centred(probe: str, t0: float) -> str:
    return f"({probe}-{_num(t0)})" if t0 >= 0 else f"({probe}+{_num(-t0)})"


def fit_static(ds: Dataset, channel: str, *, probe: str | None = None, t0_c: float = 25.0, order: int = 3,
               bin_c: float | None = 0.5, **opts: Any) -> FitResult:
    """S000 eq 3 (static cubic about t0 = 25 C) in the channel's own probe."""
    probe, source = _own_probe(ds, channel, probe)
    c = _centred(probe, t0_c)
    terms = [(f"A{j}", c if j == 1 else f"{c}^{j}") for j in range(1, order + 1)]
    return fit_linear_terms("static", ds, channel, terms=terms, intercept="A0", probe=probe, bin_c=bin_c,
                            extra_definition={"equation": "S000 eq 3", "t0_c": float(t0_c), "order": order,
                                              "probe_source": source},
                            **opts)


def fit_dynamic(ds: Dataset, channel: str, *, probe: str | None = None, grad: tuple[str, str] | None | str = "auto",
                t0_c: float | str = 25.0, l: int = 1, m: int = 1, n: int = 1, **opts: Any) -> FitResult:  # noqa: E741
    """S000 eq 4 (l = m = n = 1) and its polynomial generalisation eq 5, in the channel's own probe t_i
    (gradient ``auto``: that probe minus the first other probe)."""
    probe, source = _own_probe(ds, channel, probe)
    if grad == "auto":
        others = [p for p in ds.temp_names() if p != probe]
        grad = (probe, others[0]) if others else None
    if t0_c == "power_on":
        temp = np.asarray(ds[f"temp_{probe}"], dtype=np.float64)
        finite = temp[np.isfinite(temp)]
        if not finite.size:
            raise DataFormatError(f"temp_{probe} has no valid value")
        t0 = float(finite[0])
    else:
        t0 = float(t0_c)

    def names(letter: str, order: int) -> list[str]:
        return [letter] if order == 1 else [f"{letter}{j}" for j in range(1, order + 1)]

    def powered(expr: str, j: int) -> str:
        return expr if j == 1 else f"{expr}^{j}"

    c = _centred(probe, t0)
    terms = [(nm, powered(c, j)) for j, nm in enumerate(names("k", l), start=1)]
    if grad is not None:
        a, b = (_check_probe(ds, g) for g in grad)
        terms += [(nm, powered(f"({a}-{b})", j)) for j, nm in enumerate(names("p", m), start=1)]
    terms += [(nm, powered(f"d{probe}", j)) for j, nm in enumerate(names("q", n), start=1)]
    extra = {"equation": "S000 eq 4" if (l, m, n) == (1, 1, 1) else "S000 eq 5", "t0_c": t0,
             "t0_source": "power_on" if t0_c == "power_on" else "fixed", "orders": {"l": l, "m": m, "n": n},
             "gradient": list(grad) if grad else None, "probe_source": source}
    return fit_linear_terms("dynamic", ds, channel, terms=terms, intercept="B0", probe=probe,
                            extra_definition=extra, **opts)


def fit_patent37(ds: Dataset, channel: str, *, probes: list[str] | None = None, t0_c: float = 25.0,
                 **opts: Any) -> FitResult:
    """S001 37-term four-probe model, centred temperatures, rates in C/min."""
    probes = list(probes or ["t1", "t2", "t3", "t4"])
    if len(probes) != 4:
        raise DataFormatError(f"patent37 needs 4 probes, have {probes}")
    terms: list[tuple[str, str]] = []
    for p in probes:
        _check_probe(ds, p)
        c = _centred(p, t0_c)
        r = f"d{p}"
        tr = f"{c}*{r}"
        for expr in (c, f"{c}^2", f"{c}^3", r, f"{r}^2", f"{r}^3", tr, f"({tr})^2", f"({tr})^3"):
            terms.append((f"a{len(terms) + 1}", expr))
    # the terms keep the patent order of ``probes``; the channel's own probe (when among them) is the
    # recorded probe and spans the (T, dT/dt) validity hull
    own, source = _own_probe(ds, channel, None)
    if own not in probes:
        own, source = probes[0], "first of probes (the channel's own probe is not among them)"
    return fit_linear_terms("patent37", ds, channel, terms=terms, intercept="a0", probe=own,
                            extra_definition={"equation": "S001 37-term", "t0_c": float(t0_c), "probes": probes,
                                              "centred": "T -> T - t0", "probe_source": source}, **opts)


def fit_formula(ds: Dataset, channel: str, *, formula: str, probe: str | None = None, **opts: Any) -> FitResult:
    """Intercept plus user terms (``bench.fit.formula`` grammar).  ``tc``/``dtc`` are the channel's own
    probe (``probe=`` when given, else the data's ``channel_probes`` map, else the default); the
    definition records it as ``channel_probe`` and the resolved terms name it."""
    needs_own = uses_channel_probe(formula)
    source = None
    if probe is not None or needs_own:
        probe, source = _own_probe(ds, channel, probe)
    elif ds.temp_names():
        try:          # only spans the validity hull here: a formula without tc need not have it
            probe, source = _own_probe(ds, channel, None)
        except DataFormatError:
            probe = None
    extra: dict[str, Any] = {"probe_source": source} if source is not None else {}
    if needs_own:
        extra["channel_probe"] = probe
    return fit_linear_terms("formula", ds, channel, formula=formula, probe=probe,
                            extra_definition={**extra, **opts.pop("extra_definition", {})}, **opts)


for _name, _fit, _desc, _needs in (
        ("static", fit_static, "S000 eq 3 static cubic about t0 = 25 C", _probe_needs),
        ("dynamic", fit_dynamic, "S000 eq 4 / eq 5 dynamic model (T - t0, gradient, dT/dt)", _probe_needs),
        ("patent37", fit_patent37, "S001 37-term four-probe model", _patent37_needs),
        ("formula", fit_formula, "intercept + user terms", _needs_gyro)):
    register_model(_name, _fit, predict_linear, description=_desc, needs=_needs)


def signal_of(result: FitResult, key: str) -> list[float] | None:
    """Fitted range of a signal key (e.g. ``signal_key({"op": "temp", "column": "temp_t1"})``)."""
    return result.validity.get("signals", {}).get(key)


__all__ = ["register_model", "registered_models", "fit_model", "predict", "compensate", "prepare_fit_data",
           "fit_linear_terms", "predict_linear", "linear_validity", "inside_hull", "fit_static", "fit_dynamic",
           "fit_patent37", "fit_formula", "signal_key", "signal_of"]
