"""Suspension gaps on the SQL store: frames that stop while the run is suspended are one gap row of
kind ``suspension`` (not ``link``), counted; a gap outside any suspension keeps its own kind.  And the
store's checkpoints keep a run's percent and its elapsed bench time from one instant."""
from __future__ import annotations

import pytest
from sqlalchemy import select

from bench.engine.sqlstore import SqlRunStore, new_run
from bench.storage import queries
from bench.storage.models import Step
from tests.test_engine_doubles import Bench, Scripted
from tests.test_engine_suspend import RECORD

RATE_HZ = 20.0


def _run(db, actions) -> list:
    bench = Bench(settle_s=30.0)
    bench.link.rate_hz = RATE_HZ
    rid = new_run(db, procedure="suspend-gaps", parameters={}, config_snapshot={}, gyro_id="G-S",
                  bench_name="doubles")
    bench.store = SqlRunStore(db, geometry=bench.config.turntable.geometry, nominal_rate_hz=RATE_HZ)
    try:
        assert bench.engine(Scripted(bench.clock, actions(bench))).run(str(rid), RECORD) == "completed"
    finally:
        bench.store.close(rid)
    with db.session() as s:
        return queries.list_gaps(s, rid)


def test_frames_stopped_while_suspended_are_one_suspension_gap(db):
    def actions(bench):
        def silent(on):
            return lambda: setattr(bench.link, "silent", on)
        return [(100.0, silent(True)), (300.0, silent(False))]

    (gap,) = _run(db, actions)
    assert gap.reason == "suspension"
    # the double's counter stands still while silent: the counted clock settles the 200 s in whole turns
    assert gap.frames_missing == pytest.approx(200 * RATE_HZ, abs=128)
    assert gap.t_to - gap.t_from == pytest.approx(200.0, abs=1.0)


def test_a_reported_link_gap_while_suspended_is_the_same_one_row(db):
    def actions(bench):
        def down():
            bench.link.silent = True
            bench.link.stats.link_gaps.append((bench.clock.now(), bench.clock.now() + 50.0))

        def up():
            bench.link.silent = False
        return [(100.0, down), (150.0, up)]

    (gap,) = _run(db, actions)
    assert gap.reason == "suspension"
    assert gap.frames_missing == pytest.approx(50 * RATE_HZ, abs=128)


def test_the_last_checkpoint_leaves_the_final_elapsed_time_beside_the_final_percent(db):
    """The run page reads the percent (``runs.progress``) and the elapsed / remaining bench time
    (``live["progress"]``) of one run: each checkpoint writes both, so a run that ended between two of
    the worker's publishes (here: no worker publishes at all) still shows its whole elapsed time."""
    bench = Bench(settle_s=30.0)
    rid = new_run(db, procedure="suspend-gaps", parameters={}, config_snapshot={}, gyro_id="G-S", bench_name="doubles")
    bench.store = SqlRunStore(db, geometry=bench.config.turntable.geometry, nominal_rate_hz=RATE_HZ)
    try:
        assert bench.engine(Scripted(bench.clock, [])).run(str(rid), RECORD) == "completed"
    finally:
        bench.store.close(rid)
    with db.session() as s:
        run = queries.get_run(s, rid)
        steps = s.scalars(select(Step).where(Step.run_id == rid)).all()
        progress, percent = (run.live or {}).get("progress") or {}, 100.0 * run.progress
    assert percent == pytest.approx(100.0) and progress.get("percent") == pytest.approx(percent), progress
    assert progress["remaining_bench_s"] == 0.0
    span = max(st.finished_t for st in steps) - min(st.started_t for st in steps)
    assert span > 100.0 and progress["elapsed_bench_s"] >= span, (progress, span)
