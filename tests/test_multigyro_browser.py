"""The run page of a multi-gyro run in headless Chromium against the real service: ``bench serve
--sim-gyros 3`` (API + worker on a seeded simulated fixture of three gyros in lockstep, see
tests/browser_support.py).  A run naming three gyros is started with ``gyro_ids``; with the bench time
held at a known instant of its soak the page lists each gyro (its slot, its ID, its own run, its state,
its frames) and plots each gyro's 1-s means; after the run ends every gyro shows its final state.
Screenshots go to ``test-artifacts/dashboard/`` (multigyro-*.png)."""
from __future__ import annotations

import pytest

from tests.browser_support import T0, TOKENS, chromium_context, dashboard_service, get_json, post_json, shot, use_token

GYROS = ["MG-A", "MG-B", "MG-C"]
# bench time: soak 72 s + warm-up 60 s + ramp 30 -> 27 C at 3 C/min 60 s + hold 60 s
PARAMS = {"orientation": None, "start_c": 30, "soak_h": 0.02, "warmup_min": 1, "rate_c_per_min": 3, "end_c": 27,
          "final_hold_min": 1}
HOLD_AT = T0 + 240.0


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    with dashboard_service(tmp_path_factory.mktemp("multidash"), hold_at=HOLD_AT, serve_args=("--sim-gyros", "3")) as dash:
        yield dash


def _unit_points(page, slot: str) -> int:
    return int(page.get_attribute(f"#plot-unit-{slot}", "data-points") or 0)


def test_run_page_shows_each_gyro_state_and_plot(service):
    bench = get_json(f"{service.base}/benches", TOKENS["viewer"])["benches"][0]["name"]
    run = post_json(f"{service.base}/runs", {"procedure": "thermal_ramp", "bench": bench, "gyro_ids": GYROS,
                                             "params": PARAMS}, TOKENS["operator"])
    with chromium_context({"width": 1280, "height": 1000}) as context:
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        try:
            page.goto(f"{service.base}/ui/runs/{run['id']}")
            use_token(page, TOKENS["viewer"])
            service.hold_at(HOLD_AT)
            # held mid-run: every gyro listed with its own run and state, and plotted
            page.wait_for_selector("#units-table tbody tr[data-slot='g3']")
            page.wait_for_function("() => document.getElementById('run-status').textContent === 'running'")
            page.wait_for_function("() => ['g1', 'g2', 'g3'].every((s) => "
                                   "Number(document.getElementById('plot-unit-' + s).dataset.points) > 20)")
            rows = page.locator("#units-table tbody tr")
            assert rows.count() == 3
            listed = [[c.strip() for c in rows.nth(k).locator("td").all_inner_texts()] for k in range(3)]
            assert [r[:2] for r in listed] == [["g1", "MG-A"], ["g2", "MG-B"], ["g3", "MG-C"]]
            assert all(r[3] == "running" and int(r[4]) > 20 for r in listed), listed
            page.wait_for_function("() => ['g1', 'g2', 'g3'].every((s) => "
                                   "Number(document.getElementById('plot-unit-probes-' + s).dataset.points) > 20) && "
                                   "Number(document.getElementById('plot-chamber').dataset.points) > 20")
            for slot in ("g1", "g2", "g3"):
                assert set(page.get_attribute(f"#plot-unit-{slot}", "data-series").split(",")) >= {"x", "y", "z"}
                assert "t1" in page.get_attribute(f"#plot-unit-probes-{slot}", "data-series").split(",")
            # the run-wide probe and gyro plots give way to each gyro's own
            assert page.locator("#card-probes").is_hidden() and page.locator("#card-gyro").is_hidden()
            page.locator("#units-card").scroll_into_view_if_needed()
            shot(page, "multigyro-run-held")
            # each gyro's own run page is one click away
            unit_run = page.get_attribute("#units-table tbody tr[data-slot='g2'] td:nth-child(3) a", "href")
            assert unit_run.startswith("/ui/runs/") and unit_run != f"/ui/runs/{run['id']}"

            service.release()
            page.wait_for_function("() => document.getElementById('run-status').textContent === 'completed'")
            page.wait_for_function("() => [...document.querySelectorAll('#units-table tbody tr')].every("
                                   "(r) => r.children[3].textContent.trim() === 'completed')")
            # every gyro's plots loaded once the run ended (their final data), each with all its series
            page.wait_for_selector("#unit-plots[data-loaded-for='completed']")
            for slot in ("g1", "g2", "g3"):
                assert set(page.get_attribute(f"#plot-unit-probes-{slot}", "data-series").split(",")) >= {
                    "gyro sensor", "t1", "t2", "t3", "t4"}
            # the fit step fitted each gyro's own run: one row per gyro
            page.wait_for_selector("#run-fits tr[data-slot='g3']")
            fit_rows = [page.text_content(f"#run-fits tr[data-slot='{slot}'] td:nth-child(2)") for slot in ("g1", "g2", "g3")]
            assert fit_rows == ["g1 (MG-A)", "g2 (MG-B)", "g3 (MG-C)"]
            # the sampling card lists each gyro's probes and frames (the parent run stores none itself)
            sampled = page.locator("#sampling-table tbody td:first-child").all_inner_texts()
            assert [name for name in sampled if name.startswith("g")] == [
                f"{slot}: {what}" for slot in ("g1", "g2", "g3") for what in ("probes (bus reads)", "gyro frames")]
            assert "Gyro frames" not in sampled and "Probes (bus reads)" not in sampled
            shot(page, "multigyro-run-completed")
            assert errors == []
        except BaseException:
            shot(page, "multigyro-failure")
            raise
