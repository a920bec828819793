"""Self-contained HTML page of a close-the-loop analysis: residual before/after against time, T and
dT/dt (100-s means, before and after in panels on one scale), Allan deviation before/after, the effects
added with their evidence, and the findings."""
from __future__ import annotations

import html
from typing import Any

import numpy as np

from bench.fit import prep
from bench.fit.base import Dataset
from bench.fit.closeloop_search import cv_gain_text
from bench.fit.report import _CSS, html_table, plot_adev, plot_against, plot_before_after
from bench.signal import run_segments


def _section(label: str, data: Dataset, before: np.ndarray, after: np.ndarray, probe: str, window_s: float) -> str:
    t = np.asarray(data.time, float)
    segments = run_segments(t)
    parts = [f"<h3>{html.escape(label)} run</h3>",
             plot_before_after(t, before, after, f"{label}: residual against time (100-s means)",
                               labels=("before (declared model)", "after (with effects added)"), segments=segments)]
    if f"temp_{probe}" in data:
        temp = np.asarray(data[f"temp_{probe}"], float)
        rate = prep.rate_c_per_min(t, temp, window_s)
        parts.append(plot_against(t, {"before": before, "after": after},
                                  {f"temp_{probe} (C)": temp, f"dT/dt (C/min, over {window_s:g} s)": rate},
                                  f"{label}: residual against the model's temperature and its rate", segments=segments))
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    parts.append(plot_adev({"before": before[np.isfinite(before)], "after": after[np.isfinite(after)]},
                           1.0 / step, f"{label}: Allan deviation before / after"))
    return "\n".join(parts)


def render_close_loop_report(report: dict[str, Any], train: Dataset, validate: Dataset,
                             title: str = "Close-the-loop report") -> str:
    body = [f"<h1>{html.escape(title)}</h1>",
            f"<p>Declared model: <code>{html.escape(str(report['model']))}</code></p>"]
    glitches = [(run, col, info["samples"], ", ".join(f"{t:g}" for t in info["time_s"]))
                for run, cols in (report.get("glitches_removed") or {}).items() for col, info in cols.items()]
    if glitches:
        body.append(html_table(("run", "column", "samples", "first at (s)"), glitches,
                               caption="isolated glitches set missing before the analysis"))
    for ch, r in report["channels"].items():
        body.append(f"<h2>Channel {html.escape(ch)}: {html.escape(r['verdict'])}</h2>")
        body.append(f"<p>{html.escape(r['findings'])}</p>")
        rows = [(k, r["before"][k], r["after"][k]) for k in r["before"]]
        floor = r.get("noise_floor", {})
        interval = floor.get("interval_dph", [float("nan"), float("nan")])
        rows.append(("noise floor, std of 100-s means over the validation record", r["noise_floor_dph"],
                     f"90 % interval {interval[0]:.4g} .. {interval[1]:.4g}"))
        body.append(html_table(("metric (deg/h; validation_* = in-range part, validation_all_* = whole run as "
                                "deployed)", "before", "after"), rows, caption="error before / after"))
        outside = r.get("validation_range", {}).get("outside", {})
        if outside:
            body.append(html_table(
                ("declared input", "training range", "validation range", "below (%)", "above (%)"),
                [(k, f"{o['train_range'][0]:.4g} .. {o['train_range'][1]:.4g}",
                  f"{o['validation_range'][0]:.4g} .. {o['validation_range'][1]:.4g}",
                  100 * o["fraction_below"], 100 * o["fraction_above"]) for k, o in outside.items()],
                caption=f"validation outside the training range (coverage {100 * r['validation_range']['coverage']:.1f} %)"))
        if r.get("decisions"):
            body.append(html_table(("decision", "run used"), list(r["decisions"].items()),
                                   caption="which decision used which run"))
        if r["effects_added"]:
            body.append(html_table(
                ("#", "kind", "parameters", "terms", "delta-BIC", "HAC p", "cross-validated error", "validation std100 (deg/h)"),
                [(i, e["kind"], ", ".join([f"{k}={v}" for k, v in e["params"].items()] +
                                          ([f"start on validation={e['start_on_validation']}"]
                                           if e.get("start_on_validation") else []) +
                                          ([f"start offset on validation={e['start_offset_on_validation_dph']:+.3g} deg/h"]
                                           if "start_offset_on_validation_dph" in e else [])), ", ".join(e["terms"]),
                  e["evidence"]["delta_bic"], e["evidence"]["hac_wald_p"], cv_gain_text(e["evidence"]),
                  e["validation_std100_dph"])
                 for i, e in enumerate(r["effects_added"], 1)], caption="effects added (chosen on train, confirmed on validation)"))
        if r.get("effects_not_generalised"):
            body.append(html_table(
                ("kind", "parameters", "status", "validation std100 with / without (deg/h)"),
                [(e["kind"], ", ".join(f"{k}={v}" for k, v in e["params"].items()), e["status"],
                  f"{e['validation_std100_with_dph']:.4g} / {e['validation_std100_without_dph']:.4g}")
                 for e in r["effects_not_generalised"]], caption="chosen on train, left out"))
        body.append(html_table(("term", "coefficient"), list(r["final_coefficients"].items()),
                               caption="final model coefficients"))
        residuals = r.get("_residuals")
        if residuals:
            probe = r.get("primary_probe") or (train.temp_names() or [""])[0]
            window = float(r.get("rate_window_s", 120.0))
            for label, data, idx in (("training", train, 0), ("validation", validate, 1)):
                body.append(_section(label, data, residuals["before"][idx], residuals["after"][idx], probe, window))
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")
