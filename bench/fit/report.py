"""Self-contained HTML report of fitted models (no external resources: plots are SVG drawn by
``bench.fit.svgplot`` and embedded as base64 ``data:`` images; no CDN, no scripts).

Reusable pieces (the close-the-loop feature uses them): ``plot_temperatures``, ``plot_before_after``,
``plot_against``, ``plot_residuals``, ``plot_adev`` return an ``<img>`` HTML snippet; ``html_table``
and ``coefficient_table`` return escaped ``<table>`` snippets; ``series_metrics`` returns the numbers.

Plots are drawn for the full width of the page (``_CSS``).  Before and after are drawn as 100-s means
in panels sharing one scale (one above the other against time, side by side against a regressor), so
the one does not hide the other.

Metrics (calibration-notes lessons 6, 7): RMS, peak-to-peak, bias stability as the std of 100-s means
(GJB 2426A convention), and the minimum of the overlapping Allan deviation (allantools ``oadev``,
``data_type="freq"``, octave taus -- never "all").  Allan deviation before (raw) and after
(compensated) is plotted per model.
"""
from __future__ import annotations

import html
from typing import Any, Callable, Sequence

import numpy as np

from bench.fit.base import Dataset, FitResult, format_channel_probes
from bench.fit.svgplot import COLORS, FLAG_COLOR, Figure, svg_img
from bench.signal import (
    DEFAULT_RATE_METHOD,
    allan_deviation,
    block_means,
    run_segments,
    smoothed_temperature,
    temperature_rate,
)

Prediction = tuple[np.ndarray, np.ndarray]
PredictFn = Callable[[FitResult, Dataset], Prediction]

MAX_PLOT_POINTS = 4000
BLOCK_S = 100.0                 # before / after plots show means over this many seconds


# --------------------------------------------------------------------------------------------
# Plot helpers (each returns an <img> snippet)
# --------------------------------------------------------------------------------------------


def _thin(n: int, max_points: int = MAX_PLOT_POINTS) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / max_points))))


def _with_gaps(x: np.ndarray, y: np.ndarray, segments: list[slice] | None) -> tuple[np.ndarray, np.ndarray]:
    """x and y with a NaN between segments, so a line is not drawn across a gap."""
    if not segments or len(segments) < 2:
        return x, y
    xs, ys = [], []
    for seg in segments:
        xs += [x[seg], [np.nan]]
        ys += [y[seg], [np.nan]]
    return np.concatenate(xs[:-1]), np.concatenate(ys[:-1])


def _std(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(np.std(finite, ddof=1)) if finite.size > 1 else float("nan")


def plot_temperatures(dataset: Dataset, title: str = "Temperatures") -> str:
    t = np.asarray(dataset.time, float)
    fig = Figure(title)
    ax = fig.panel(xlabel="time (h)", ylabel="temperature (C)")
    s = _thin(t.size)
    for name in dataset.temp_names():
        ax.line(t[s] / 3600.0, np.asarray(dataset[f"temp_{name}"], float)[s], label=name)
    return svg_img(fig.render(), title)


def plot_before_after(time_s: np.ndarray, before: np.ndarray, after: np.ndarray, title: str,
                      unit: str = "deg/h", labels: tuple[str, str] = ("before", "after"),
                      segments: list[slice] | None = None, block_s: float = BLOCK_S) -> str:
    """``before`` and ``after`` against time as ``block_s``-s means (each block inside one segment, see
    ``bench.signal.block_means``), in two panels one above the other sharing both axes: the change in
    spread reads at a glance and neither series hides the other.  Each panel says its std of the means."""
    t = np.asarray(time_s, float)
    bm = block_means(t, {"before": np.asarray(before, float), "after": np.asarray(after, float)}, block_s, segments)
    fig = Figure(title, sharex=True, sharey=True, panel_height_px=200)
    for key, label, color in zip(("before", "after"), labels, COLORS):
        y = bm.columns[key]
        x, y = _with_gaps(bm.time_s / 3600.0, y, bm.segments)
        fig.panel(f"{label}: {block_s:g}-s means, std {_std(bm.columns[key]):.3g} {unit}", xlabel="time (h)",
                  ylabel=unit, zero_line=True).line(x, y, color=color)
    return svg_img(fig.render(), title)


def plot_against(time_s: np.ndarray, residuals: dict[str, np.ndarray], regressors: dict[str, np.ndarray],
                 title: str, unit: str = "deg/h", segments: list[slice] | None = None,
                 block_s: float = BLOCK_S) -> str:
    """Each residual (before, after...) against each regressor (T, dT/dt...) as ``block_s``-s means of
    both: one row per regressor, one panel per residual side by side, all on one residual scale."""
    t = np.asarray(time_s, float)
    cols = {f"r:{k}": np.asarray(v, float) for k, v in residuals.items()}
    cols.update({f"x:{k}": np.asarray(v, float) for k, v in regressors.items()})
    bm = block_means(t, cols, block_s, segments)
    fig = Figure(title, columns=len(residuals), sharey=True, panel_height_px=230)
    for xlabel in regressors:
        x = bm.columns[f"x:{xlabel}"]
        for (name, _), color in zip(residuals.items(), COLORS):
            y = bm.columns[f"r:{name}"]
            fig.panel(f"{name}: {block_s:g}-s means, std {_std(y):.3g} {unit}", xlabel=xlabel,
                      ylabel=f"residual ({unit})", zero_line=True).points(x, y, color=color)
    return svg_img(fig.render(), title)


def plot_residuals(residual: np.ndarray, x: np.ndarray, xlabel: str, title: str,
                   unit: str = "deg/h", flagged: np.ndarray | None = None) -> str:
    r = np.asarray(residual, float)
    x = np.asarray(x, float)
    fig = Figure(title)
    ax = fig.panel(xlabel=xlabel, ylabel=f"residual ({unit})", zero_line=True)
    s = _thin(r.size)
    ax.points(x[s], r[s])
    if flagged is not None and np.any(flagged):
        f = np.nonzero(np.asarray(flagged, bool))[0]
        f = f[_thin(f.size)]
        ax.points(x[f], r[f], label="outside validity", color=FLAG_COLOR)
    return svg_img(fig.render(), title)


def _adev_or_empty(series: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """``bench.signal.allan_deviation`` (taus, adev); empty when the series is too short to have one."""
    try:
        taus, devs, _, _ = allan_deviation(series, rate_hz)
    except ValueError:
        return np.zeros(0), np.zeros(0)
    return taus, devs


def plot_adev(series: dict[str, np.ndarray], rate_hz: float, title: str = "Allan deviation",
              unit: str = "deg/h") -> str:
    fig = Figure(title)
    ax = fig.panel(xlabel="tau (s)", ylabel=f"Allan deviation ({unit})", xlog=True, ylog=True)
    for label, values in series.items():
        taus, devs = _adev_or_empty(values, rate_hz)
        if taus.size:
            ax.line(taus, devs, label=label)
    return svg_img(fig.render(), title)


# --------------------------------------------------------------------------------------------
# Tables and metrics
# --------------------------------------------------------------------------------------------


def _fmt(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return "nan" if not np.isfinite(value) else f"{float(value):.6g}"
    if isinstance(value, (list, tuple)) and len(value) > 8:
        return f"[{len(value)} items]"
    return str(value)


def html_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], caption: str | None = None,
               css_class: str = "tbl") -> str:
    out = [f'<table class="{html.escape(css_class, quote=True)}">']
    if caption:
        out.append(f"<caption>{html.escape(caption)}</caption>")
    out.append("<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in headers) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _signal_label(key: str) -> tuple[str, str]:
    """A validity signal key (``temp:temp_t1``, ``rate:temp_t1``, ``column:humidity``) as words and unit."""
    op, _, column = key.partition(":")
    if op == "temp":
        return column, "C"
    if op == "rate":
        return f"dT/dt of {column}", "C/min"
    return column or key, ""


def _span(lo: float, hi: float, unit: str) -> str:
    return f"{float(lo):.4g} .. {float(hi):.4g}" + (f" {unit}" if unit else "")


def validity_rows(validity: dict[str, Any]) -> list[tuple[str, str]]:
    """A fit's validity as rows people read: one per signal range (``temp_t1`` | ``-26.56 .. 51.25 C``),
    the (T, dT/dt) hull as its vertex count and inputs, the rest as values (never a dict or list)."""
    rows: list[tuple[str, str]] = []
    for key, (lo, hi) in (validity.get("signals") or {}).items():
        label, unit = _signal_label(key)
        rows.append((f"range of {label}", _span(lo, hi, unit)))
    if validity.get("hull"):
        inputs = " and ".join(_signal_label(k)[0] for k in validity.get("hull_signals") or ())
        rows.append(("hull", f"polygon of {len(validity['hull'])} vertices" + (f" in {inputs}" if inputs else "")))
    for key, value in validity.items():
        if key in ("signals", "hull", "hull_signals"):
            continue
        if key in ("tmin_c", "tmax_c") and isinstance(value, (int, float)):
            rows.append((key, f"{float(value):.4g} C"))
        elif isinstance(value, dict):
            rows.extend((f"{key}: {k}", _fmt(v)) for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            rows.append((key, ", ".join(_fmt(v) for v in value) if len(value) <= 8 else f"{len(value)} values"))
        else:
            rows.append((key, _fmt(value)))
    return rows


def coefficient_table(result: FitResult) -> str:
    rows = [(name, value, result.units.get(name, "")) for name, value in result.coefficients.items()]
    return html_table(("term", "value", "unit"), rows, caption=f"{result.model} / {result.channel}: coefficients",
                      css_class="coef")


def series_metrics(time_s: np.ndarray, values: np.ndarray, window_s: float = 100.0) -> dict[str, float]:
    """RMS, peak-to-peak, std of ``window_s`` means, Allan-deviation minimum."""
    t = np.asarray(time_s, float)
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    t, v = t[ok], v[ok]
    if v.size == 0:
        return {"rms": float("nan"), "p2p": float("nan"), "std100": float("nan"), "adev_min": float("nan")}
    means = block_means(t, {"v": v}, window_s, run_segments(t)).columns["v"]
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    _, devs = _adev_or_empty(v, 1.0 / step if step > 0 else 1.0)
    return {"rms": float(np.sqrt(np.mean(v ** 2))), "p2p": float(v.max() - v.min()),
            "std100": float(np.std(means, ddof=1)) if means.size > 1 else float("nan"),
            "adev_min": float(devs.min()) if devs.size else float("nan")}


def _temperature_for(result: FitResult, dataset: Dataset) -> tuple[np.ndarray | None, str]:
    d = result.definition
    col = d.get("temperature_column")
    if col and col in dataset:
        return np.asarray(dataset[col], float), col
    src = d.get("temperature_source") or {}
    if src.get("kind") == "reverse_cubic" and src.get("freq_column") in dataset:
        u = (np.asarray(dataset[src["freq_column"]], float) - src["f_centre_hz"]) / src["f_scale_hz"]
        return np.polynomial.polynomial.polyval(u, src["coefficients"]), f"T({src['freq_column']})"
    names = dataset.temp_names()
    if names:
        return np.asarray(dataset[f"temp_{names[0]}"], float), f"temp_{names[0]}"
    return None, ""


def _rate_regressor(result: FitResult) -> tuple[str, float]:
    """(rate method, window s) of the dT/dt the model used (``definition["rate_method"]`` and
    ``["rate_window_s"]``; results stored before these keys: the linear models' ``rate_filter`` window
    with the centred slope, the savgol2 models' ``average_s``)."""
    d = result.definition
    if "rate_method" in d:
        return str(d["rate_method"]), float(d["rate_window_s"])
    if isinstance(d.get("rate_filter"), dict):
        return DEFAULT_RATE_METHOD, float(d["rate_filter"]["window_s"])
    return "savgol2", float(d.get("average_s", 100.0) or 100.0)


def _unit_of(result: FitResult) -> str:
    return "C" if result.target.startswith("temp_") else ("Hz" if result.target.startswith("freq_") else "deg/h")


# --------------------------------------------------------------------------------------------
# Page
# --------------------------------------------------------------------------------------------

_CSS = """
body{font-family:sans-serif;margin:1.5em}
table{border-collapse:collapse;margin:0.6em 0}
th,td{border:1px solid #bbb;padding:2px 8px;text-align:right}
th{background:#eee} caption{font-weight:bold;text-align:left}
img{display:block;margin:0.4em 0;width:100%;height:auto}
.note{color:#555;font-size:90%}
"""


def _dataset_section(label: str, result: FitResult, dataset: Dataset, pred: Prediction,
                     metric_rows: list[list[Any]]) -> str:
    unit = _unit_of(result)
    if result.target not in dataset or "time_s" not in dataset:
        return f"<p class='note'>{html.escape(label)}: column {html.escape(result.target)} missing</p>"
    t = np.asarray(dataset.time, float)
    measured = np.asarray(dataset[result.target], float)
    values, flagged = (np.asarray(a) for a in pred)
    residual = measured - values
    name = f"{result.model} / {result.channel} - {label}"
    segs = run_segments(t, dataset.columns.get("run"))
    parts = [f"<h3>{html.escape(name)}</h3>",
             plot_before_after(t, measured - np.nanmean(measured), residual, f"{name}: raw vs compensated", unit,
                               ("raw - mean", "compensated"), segs)]
    temp, temp_label = _temperature_for(result, dataset)
    if temp is not None:
        method, window = _rate_regressor(result)
        finite = np.isfinite(temp)
        if finite.sum() >= 2 and not finite.all():    # missed probe readings: bridge them for the plot
            temp = np.interp(t, t[finite], temp[finite])
        # the x axes are the regressors the model used: its temperature (smoothed by the savgol2 models)
        # and its dT/dt with the model's own rate method and window
        if method == "savgol2":
            temp = smoothed_temperature(t, temp, window, segs)
        rate = temperature_rate(t, temp, window, method=method, segments=segs)
        rate_label = f"dT/dt (C/min, {method} over {window:g} s)"
        parts.append(plot_residuals(residual, temp, f"{temp_label} (C)", f"{name}: residual vs T", unit, flagged))
        parts.append(plot_residuals(residual, rate, rate_label, f"{name}: residual vs dT/dt", unit, flagged))
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    parts.append(plot_adev({"raw": measured, "compensated": residual}, 1.0 / step if step > 0 else 1.0,
                           f"{name}: Allan deviation", unit))
    for kind, series in (("raw", measured - np.mean(measured)), ("compensated", residual)):
        m = series_metrics(t, series)
        metric_rows.append([result.model, result.channel, label, kind, m["rms"], m["p2p"], m["std100"],
                            m["adev_min"], float(np.mean(flagged)) if kind == "compensated" else ""])
    return "\n".join(parts)


def render_fit_report(results: Sequence[FitResult], train: Dataset, validation: Dataset | None = None,
                      train_predictions: Sequence[Prediction | None] | None = None,
                      validation_predictions: Sequence[Prediction | None] | None = None,
                      predict: PredictFn | None = None, title: str = "Fit report") -> str:
    """One self-contained HTML page.

    Predictions are (values, flagged) per result, in the order of ``results``; a missing one is
    computed with ``predict(result, dataset)`` when given, otherwise that section is left out."""
    def prediction(i: int, given: Sequence[Prediction | None] | None, data: Dataset) -> Prediction | None:
        # predict() may return None to leave a section out
        if given is not None and i < len(given) and given[i] is not None:
            return given[i]
        return predict(results[i], data) if predict is not None else None

    body = [f"<h1>{html.escape(title)}</h1>"]
    body.append(html_table(("dataset", "samples", "duration (h)", "meta"),
                           [(lbl, len(d), (float(d.time[-1] - d.time[0]) / 3600.0) if len(d) > 1 else 0.0,
                             "; ".join(f"{k}={format_channel_probes(v) if k == 'channel_probes' else v}"
                                       for k, v in d.meta.items()))
                            for lbl, d in (("train", train), ("validation", validation)) if d is not None],
                           caption="Data"))
    body.append("<h2>Temperatures</h2>")
    body.append(plot_temperatures(train, "Training run: temperatures"))
    if validation is not None:
        body.append(plot_temperatures(validation, "Validation run: temperatures"))

    body.append("<h2>Models</h2>")
    for r in results:
        body.append(f"<h3>{html.escape(r.model)} / {html.escape(r.channel)} &rarr; {html.escape(r.target)}</h3>")
        formula = r.definition.get("formula")
        if formula:
            body.append(f"<p><code>{html.escape(str(formula))}</code></p>")
        if r.definition.get("probe"):
            body.append(f"<p>probe: {html.escape(str(r.definition['probe']))}"
                        f" ({html.escape(str(r.definition.get('probe_source') or 'given'))})</p>")
        if r.coefficients:
            body.append(coefficient_table(r))
        body.append(html_table(("statistic", "value"), [(k, v) for k, v in r.stats.items()
                                                        if not isinstance(v, (dict, np.ndarray))],
                               caption="fit statistics", css_class="stats"))
        body.append(html_table(("validity", "value"), validity_rows(r.validity),
                               caption="validity", css_class="validity"))

    metric_rows: list[list[Any]] = []
    sections: list[str] = []
    for i, r in enumerate(results):
        for label, data, given in (("train", train, train_predictions),
                                   ("validation", validation, validation_predictions)):
            if data is None:
                continue
            pred = prediction(i, given, data)
            if pred is not None:
                sections.append(_dataset_section(label, r, data, pred, metric_rows))
    if metric_rows:
        body.append("<h2>Error before / after</h2>")
        body.append(html_table(("model", "channel", "data", "series", "RMS", "peak-peak", "std of 100-s means",
                                "ADEV min", "flagged fraction"), metric_rows, caption="metrics", css_class="metrics"))
        body.append("<h2>Plots</h2>")
        body.extend(sections)
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")
