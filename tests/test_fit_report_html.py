"""HTML fit report: self-contained, escaped, with tables and images."""
from __future__ import annotations

import re

import numpy as np

from bench.fit.fog import fit_fog_delaunay, fit_fog_stepwise, predict_fog_delaunay, predict_fog_stepwise
from bench.fit.report import html_table, plot_adev, plot_residuals, render_fit_report, series_metrics

from tests.test_fit_fog_stepwise import startup_runs

PREDICT = {"fog_stepwise": predict_fog_stepwise, "fog_delaunay": predict_fog_delaunay}


def test_report_renders_self_contained_with_tables_and_images():
    train = startup_runs(21, rho_100s=0.5, sd=0.005, starts=(-20, 20, 50))
    valid = startup_runs(22, rho_100s=0.5, sd=0.005, starts=(-20, 20, 50))
    train.meta["run"] = "A <&> B"
    results = [fit_fog_stepwise(train, "x", probe="t1"), fit_fog_delaunay(train, "x", probe="t1")]
    delaunay_valid = predict_fog_delaunay(results[1], valid)
    # stepwise: computed through predict=; Delaunay: validation prediction given, train part left out
    page = render_fit_report(results, train, valid, train_predictions=[None, None],
                             validation_predictions=[None, delaunay_valid],
                             predict=lambda r, d: PREDICT[r.model](r, d) if r.model == "fog_stepwise" else None,
                             title="FOG <start-up> & check")
    assert page.startswith("<!DOCTYPE html>")
    assert "FOG &lt;start-up&gt; &amp; check" in page and "<start-up>" not in page
    assert "A &lt;&amp;&gt; B" in page
    assert 'class="coef"' in page and 'class="metrics"' in page
    assert "T*dT" in page                       # a selected term shows in the coefficient table
    imgs = re.findall(r'<img [^>]*src="([^"]+)"', page)
    # 2 temperature plots + per (model, dataset) shown: bias, residual vs T, residual vs dT/dt, ADEV
    assert len(imgs) == 2 + 3 * 4
    assert all(src.startswith("data:image/svg+xml;base64,") for src in imgs)
    assert "http://" not in page and "https://" not in page
    assert "<script" not in page
    # compensation helps on the validation run (metrics table: raw row then compensated row)
    m_raw = series_metrics(valid.time, valid["gyro_x"] - valid["gyro_x"].mean())
    pred, _ = predict_fog_stepwise(results[0], valid)
    m_comp = series_metrics(valid.time, valid["gyro_x"] - pred)
    assert m_comp["std100"] < 0.5 * m_raw["std100"]


def test_helpers_return_snippets():
    x = np.linspace(0, 1, 500)
    snippet = plot_residuals(np.sin(x), x, "T (C)", "res <1>")
    assert snippet.startswith("<img") and 'alt="res &lt;1&gt;"' in snippet
    assert plot_adev({"a": np.random.default_rng(0).normal(size=2048)}, 1.0).startswith("<img")
    table = html_table(["a<b"], [["<x>"]])
    assert "&lt;x&gt;" in table and "a&lt;b" in table


def test_residual_plots_use_the_rate_each_model_fitted():
    """The dT/dt axis of "residual vs dT/dt" is the model's own regressor: its rate method and window."""
    from bench.fit.models import fit_model
    from bench.fit.report import _rate_regressor

    train = startup_runs(23, rho_100s=0.5, sd=0.005, starts=(-20, 20))
    fog = fit_fog_stepwise(train, "x", probe="t1", average_s=60.0)
    assert fog.definition["rate_method"] == "savgol2" and fog.definition["rate_window_s"] == 60.0
    assert _rate_regressor(fog) == ("savgol2", 60.0)
    linear = fit_model("t1 + dt1", train, "x", rate_window_s=300.0)
    assert linear.definition["rate_method"] == "centred_slope"
    assert _rate_regressor(linear) == ("centred_slope", 300.0)
    # a result stored before the keys existed: the linear models' rate_filter window, centred slope
    old = dict(linear.definition)
    del old["rate_method"], old["rate_window_s"]
    linear.definition = old
    assert _rate_regressor(linear) == ("centred_slope", 300.0)


def test_validity_reads_as_ranges_with_units_not_as_a_python_dict():
    """The fit report's validity table: one row per fitted input range, with its unit, and the hull as a
    vertex count (it printed {'temp:temp_t1': [-26.5625, 51.25], ...} and ['temp:temp_t1', 'rate:temp_t1'])."""
    from bench.fit.models import fit_model

    train = startup_runs(24, rho_100s=0.5, sd=0.005, starts=(-20, 20))
    results = [fit_model("static", train, "x"), fit_model("t1 + dt1", train, "x"),
               fit_fog_delaunay(train, "x", probe="t1")]
    page = render_fit_report(results, train)
    tables = re.findall(r'<table class="validity">.*?</table>', page, flags=re.S)
    assert len(tables) == 3
    for table in tables:
        cells = re.findall(r"<td>(.*?)</td>", table)
        assert cells and not any(c.startswith(("{", "[")) or "&#x27;" in c for c in cells), cells
    t1 = train["temp_t1"]
    assert f"<td>range of temp_t1</td><td>{t1.min():.4g} .. {t1.max():.4g} C</td>" in tables[0], tables[0]
    assert re.search(r"<td>range of dT/dt of temp_t1</td><td>-?[\d.]+ \.\. -?[\d.]+ C/min</td>", tables[1]), tables[1]
    assert re.search(r"<td>hull</td><td>polygon of \d+ vertices", page)
