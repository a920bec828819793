"""The dashboard's analysis lists, run page and close-the-loop report in headless Chromium (Debian
``chromium`` driven by PyPI ``playwright``; never ``playwright install``) against ``bench serve``.

Stored beforehand in the service's SQLite file: two measured-data runs of each of two gyros (synthetic
ramps just above the close-loop minimum lengths: the pages are under test here, not what the analysis can
resolve; gyro A's carry a hidden dT/dt effect).  Through the API the test fits two models
and closes the loop; then, in the browser: the fits list and the close-the-loop list filtered by gyro,
model and date; an analysis page whose effects are a table (no raw JSON) and whose report shows 100-s
means before and after at full width; a thermal ramp on the simulated bench whose run page keeps one
progress figure, a total equal to elapsed + remaining with the remaining time shrinking, a set-point
trace that follows the ramp, and plots that zoom, pan and read out at the pointer.
Screenshots go to ``test-artifacts/dashboard/``.
"""
from __future__ import annotations

import datetime as dt
import re

import pytest

from tests.browser_support import (ARTIFACTS, T0, TOKENS, chromium_context, dashboard_service, get_json, post_json,
                                   shot, use_token)
from tests.service_support import SAFETY_S, wait_for
from tests.synth import SHORT_TRAIN_PROFILE, SHORT_VALIDATE_PROFILE, make_run

# bench time: soak 72 s, warm-up 60 s, ramp 30 -> 12 C at 1 C/min from about T0 + 132 s to T0 + 1212 s,
# hold 120 s; the run page is read at two instants of the ramp.  Elapsed and remaining bench time come
# from the worker's live document, published about every wall second: at x120 at most (SPEED) it is at
# most about 120 bench s older than the hold when the page reads it
RAMP = {"orientation": None, "start_c": 30.0, "soak_h": 0.02, "warmup_min": 1.0, "rate_c_per_min": 1.0,
        "end_c": 12.0, "final_hold_min": 2.0}
READ_AT = (T0 + 700.0, T0 + 1200.0)
SPEED = "120"


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    from bench.commands.service import import_dataset
    from bench.storage import open_database

    tmp = tmp_path_factory.mktemp("dash-analyses")
    url = f"sqlite:///{tmp / 'bench.sqlite'}"
    db = open_database(url)
    runs = {}
    try:
        for gyro, hidden in (("GYRO-A", {"rate": 0.08}), ("GYRO-B", {})):
            train, _ = make_run(SHORT_TRAIN_PROFILE, hidden, seed=11, dt=1.0)
            val, _ = make_run(SHORT_VALIDATE_PROFILE, hidden, seed=12, dt=1.0)
            runs[gyro] = (import_dataset(db, train, gyro, source="train.csv"),
                          import_dataset(db, val, gyro, source="val.csv"))
    finally:
        db.dispose()
    with dashboard_service(tmp, url, hold_at=READ_AT[0], speed=SPEED) as dash:
        yield dash, runs


@pytest.fixture(scope="module")
def browser():
    with chromium_context({"width": 1400, "height": 900}) as context:
        yield context


def _page(browser, service_base, path, errors):
    page = browser.new_page()
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{service_base}{path}")
    use_token(page, TOKENS["operator"])
    return page


def test_fit_and_close_loop_lists_filter_and_show_tables(service, browser):
    dash, runs = service
    base = dash.base
    op = TOKENS["operator"]
    (a_train, a_val), (b_train, b_val) = runs["GYRO-A"], runs["GYRO-B"]
    for model, (train, val) in (("static", (a_train, a_val)), ("dynamic", (a_train, a_val)), ("static", (b_train, b_val))):
        post_json(f"{base}/fits", {"model": model, "run_ids": [train], "validation_run_ids": [val], "channels": ["x"]}, op)
    analyses = [post_json(f"{base}/close-loop", {"model": "static", "train_run_id": t, "validation_run_id": v,
                                             "channels": ["x"]}, op)["id"]
                for t, v in ((a_train, a_val), (b_train, b_val))]
    wait_for(lambda: all(get_json(f"{base}/close-loop/{i}", op)["status"] in ("done", "failed") for i in analyses),
             SAFETY_S, "the close-the-loop analyses to end", interval=0.5)
    today = dt.datetime.now(dt.timezone.utc).date()

    errors: list[str] = []
    page = _page(browser, base, "/ui/fits", errors)
    page.wait_for_selector("#fits-table tbody tr[data-fit]")
    assert page.locator("#fits-table tbody tr[data-fit]").count() == 3
    page.fill("#fit-filters-gyro_id", "GYRO-A")
    page.fill("#fit-filters-model", "static")
    page.click("#fit-filters button[type=submit]")
    page.wait_for_function("() => document.querySelectorAll('#fits-table tbody tr[data-fit]').length === 1")
    row = page.locator("#fits-table tbody tr[data-fit]")
    assert row.get_attribute("data-gyro") == "GYRO-A" and row.get_attribute("data-model") == "static"
    assert "deg/h" in row.text_content() and "{" not in row.text_content()
    assert "gyro_id=GYRO-A" in page.url and "model=static" in page.url     # a filtered list can be bookmarked
    shot(page, "10-fits-filtered")
    page.fill("#fit-filters-date_from", (today + dt.timedelta(days=1)).isoformat())
    page.click("#fit-filters button[type=submit]")
    page.wait_for_selector("#fits-table td.muted")                          # nothing created tomorrow
    page.fill("#fit-filters-date_from", today.isoformat())
    page.fill("#fit-filters-date_to", today.isoformat())
    page.click("#fit-filters button[type=submit]")
    page.wait_for_function("() => document.querySelectorAll('#fits-table tbody tr[data-fit]').length === 1")

    page.goto(f"{base}/ui/close-loop")
    page.wait_for_selector("#analyses-table tbody tr[data-analysis]")
    assert page.locator("#analyses-table tbody tr[data-analysis]").count() == 2
    page.fill("#analysis-filters-gyro_id", "GYRO-A")
    page.click("#analysis-filters button[type=submit]")
    page.wait_for_function("() => document.querySelectorAll('#analyses-table tbody tr[data-analysis]').length === 1")
    row = page.locator("#analyses-table tbody tr[data-analysis]")
    assert row.get_attribute("data-gyro") == "GYRO-A" and "explained" in row.text_content()
    assert "→" in row.text_content() and "deg/h" in row.text_content()
    shot(page, "11-close-loop-list")
    page.fill("#analysis-filters-model", "dynamic")                        # no analysis declared dynamic
    page.click("#analysis-filters button[type=submit]")
    page.wait_for_selector("#analyses-table td.muted")

    # --- one analysis: effects as a table, then the report with its plots
    page.goto(f"{base}/ui/close-loop/{analyses[0]}")
    page.wait_for_selector("[data-channel='x'] table.effects tr[data-effect='rate']")
    text = page.text_content("#content")
    assert '{"' not in text and "ΔBIC" in text
    shot(page, "12-close-loop-analysis")
    page.click("#load-report")
    page.wait_for_selector("#cl-report-frame")
    frame = page.frame_locator("#cl-report-frame")
    frame.locator("img").first.wait_for()
    assert frame.locator("img").count() >= 6
    # full width: every plot spans the report's width (minus its margins)
    widths = frame.locator("body").evaluate("""(body) => [...body.querySelectorAll('img')].map(
        (i) => i.getBoundingClientRect().width / body.getBoundingClientRect().width)""")
    assert widths and min(widths) > 0.9, widths
    shot(page, "13-close-loop-report")
    assert not errors, errors


def test_run_page_is_consistent_while_a_ramp_runs(service, browser):
    dash, _ = service
    base = dash.base
    run = post_json(f"{base}/runs", {"procedure": "thermal_ramp", "gyro_id": "GYRO-RUN", "bench": "sim1",
                                     "params": RAMP}, TOKENS["operator"])
    errors: list[str] = []
    page = _page(browser, base, f"/ui/runs/{run['id']}", errors)
    dash.hold_at(READ_AT[0])           # bench time stands still while the page is read
    page.wait_for_function("() => document.getElementById('run-status').textContent === 'running'")

    def sample():
        span = page.locator("#total-bench")
        e, r = float(span.get_attribute("data-elapsed") or "nan"), float(span.get_attribute("data-remaining") or "nan")
        return e, r, span.text_content()

    page.wait_for_function("() => Number(document.getElementById('total-bench').dataset.elapsed) > 450")
    # the gyro's latest 1-s mean in deg/h, as the plot shows it (not "–, –, –")
    page.wait_for_function("() => /Gyro 1-s mean\\s*-?[0-9][^–]*\\(deg\\/h\\)/.test("
                           "document.getElementById('latest').textContent)")
    e1, r1, _ = sample()
    dash.hold_at(READ_AT[1])
    page.wait_for_function(f"() => Number(document.getElementById('total-bench').dataset.elapsed) > {e1 + 300}")
    e2, r2, text = sample()
    assert e2 > e1 and r2 < r1, (e1, r1, e2, r2)          # the remaining time shrinks as time elapses
    assert "%" not in page.text_content("#live")           # one progress figure: the bar
    # the latest chamber reading names the set point the plot draws (the ramping one), beside the air
    latest = page.text_content("#latest")
    m = re.search(r"Chamber air\s*(-?[\d.]+) °C \(set point (-?[\d.]+) °C, ramping\)", latest)
    assert m and abs(float(m.group(1)) - float(m.group(2))) < 3.0, latest
    page.wait_for_function("() => (document.getElementById('plot-chamber').dataset.series || '')"
                           ".includes('set point (ramping)')")
    # the ramping set point follows the ramp: it went down from 30 C towards 12 C, as the air did
    cols = get_json(f"{base}/runs/{run['id']}/data?stream=seconds&format=json", TOKENS["viewer"])["columns"]
    pairs = [(sp, pv) for sp, pv in zip(cols["chamber_ramp_sp"], cols["chamber_pv"]) if sp is not None and pv is not None]
    ramp_sp = [sp for sp, _ in pairs]
    assert max(ramp_sp) - min(ramp_sp) > 5 and len(set(round(v, 1) for v in ramp_sp)) > 5, ramp_sp[::50]
    assert max(abs(sp - pv) for sp, pv in pairs) < 3.0           # ... and the air follows it
    # zoom, pan and read-out on the chamber plot
    plot = page.locator("#plot-chamber")
    box = plot.bounding_box()
    readouts = []
    for frac in (0.5, 0.6, 0.7, 0.4, 0.8, 0.3):      # the pointer over a sample where every series has a value
        page.mouse.move(box["x"] + box["width"] * frac, box["y"] + box["height"] * 0.5)
        page.wait_for_function("() => document.getElementById('plot-chamber').dataset.cursor !== ''")
        readouts.append(plot.get_attribute("data-cursor"))
        if "chamber air" in readouts[-1] and "set point (ramping)" in readouts[-1]:
            break
    readout = readouts[-1]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    plot.screenshot(path=str(ARTIFACTS / "15-plot-readout.png"))
    assert "°C" in readout and "chamber air" in readout and "set point (ramping)" in readout, readouts
    assert re.match(r"bench time since the first recorded second: [\d.]+ h;", readout), readout   # x with its unit
    # before the ramp (the soak at 30 C) the set-point trace goes on at the register's 30 C, not blank
    page.mouse.move(box["x"] + box["width"] * 0.06, box["y"] + box["height"] * 0.5)
    page.wait_for_function("() => document.getElementById('plot-chamber').dataset.cursor.includes('set point')")
    assert "set point (ramping): 30 °C" in plot.get_attribute("data-cursor"), plot.get_attribute("data-cursor")
    page.mouse.wheel(0, -300)
    page.wait_for_function("() => document.getElementById('plot-chamber').dataset.view !== ''")
    zoomed = plot.get_attribute("data-view")
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] * 0.4, box["y"] + box["height"] * 0.5, steps=4)
    page.mouse.up()
    assert plot.get_attribute("data-view") != zoomed                                  # panned
    shot(page, "14-run-page-zoomed")
    plot.dblclick()
    page.wait_for_function("() => document.getElementById('plot-chamber').dataset.view === ''")
    dash.release()                     # the rest of the run as fast as the host can
    page.wait_for_function("() => ['completed', 'aborted', 'failed'].includes("
                           "document.getElementById('run-status').textContent)")
    assert page.text_content("#run-status") == "completed", page.text_content("#summary")
    e3, r3, _ = sample()
    assert r3 == 0.0 and e3 >= e2
    assert not errors, errors
