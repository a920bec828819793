"""Run bookkeeping: state machine, scheduling, checkpoints, steps, events, fits."""
from __future__ import annotations

import datetime as dt

import pytest

from bench.storage import InvalidTransition, StorageError, UnknownRun, queries
from bench.storage.models import Fit, Run, RunStatus
from tests.test_storage_support import db, run_id  # noqa: F401 - fixtures


def test_run_state_machine_stamps_times_and_refuses_bad_moves(db, run_id):
    with db.session() as s:
        run = queries.set_run_status(s, run_id, "running", worker="w1")
        assert run.started_at is not None and run.finished_at is None and run.worker == "w1"
        queries.set_run_status(s, run_id, "paused")
        queries.set_run_status(s, run_id, "running")
        queries.set_run_status(s, run_id, "completed")
    with db.session() as s:
        run = queries.get_run(s, run_id)
        assert run.status == "completed" and run.finished_at >= run.started_at
        with pytest.raises(InvalidTransition, match="from 'completed' to 'running'.*final"):
            queries.set_run_status(s, run_id, "running")
        with pytest.raises(ValueError):
            queries.set_run_status(s, run_id, "exploded")
        with pytest.raises(UnknownRun):
            queries.get_run(s, 987654)


def test_claim_next_run_respects_start_at_and_order(db):
    now = dt.datetime(2030, 1, 1, tzinfo=dt.timezone.utc)
    with db.session() as s:
        for r in queries.list_runs(s, status="queued"):
            queries.set_run_status(s, r.id, "aborted")
        later = queries.create_run(s, procedure="later", start_at=now + dt.timedelta(hours=1)).id
        first = queries.create_run(s, procedure="first", start_at=now - dt.timedelta(hours=1)).id
        unscheduled = queries.create_run(s, procedure="whenever").id
    with db.session() as s:
        got = queries.claim_next_run(s, "worker-A", now=now)
        assert got.id == first and got.status == "running" and got.worker == "worker-A"
    with db.session() as s:
        assert queries.claim_next_run(s, "worker-B", now=now).id == unscheduled
    with db.session() as s:
        assert queries.claim_next_run(s, "worker-B", now=now) is None
        assert queries.claim_next_run(s, "worker-B", now=now + dt.timedelta(hours=2)).id == later
    with db.session() as s:
        queries.heartbeat(s, first, "worker-A")
        with pytest.raises(StorageError, match="not owned"):
            queries.heartbeat(s, first, "worker-B")
        assert first in [r.id for r in queries.stale_runs(s, dt.timedelta(seconds=-1))]



def test_claim_next_run_serves_one_bench_scheduled_first_then_queued_in_creation_order(db):
    """The worker's claim: scheduled runs by start_at once due, then unscheduled ones by creation,
    never another bench's run; the extra values (the worker's config snapshot) are stored."""
    now = dt.datetime(2031, 1, 1, tzinfo=dt.timezone.utc)
    with db.session() as s:
        for r in queries.list_runs(s, status="queued"):
            queries.set_run_status(s, r.id, "aborted")
        other = queries.create_run(s, procedure="other", bench_name="bench-B",
                                   start_at=now - dt.timedelta(hours=3)).id
        queued_1 = queries.create_run(s, procedure="q1", bench_name="bench-A").id
        queued_2 = queries.create_run(s, procedure="q2", bench_name="bench-A").id
        due_late = queries.create_run(s, procedure="d2", bench_name="bench-A", start_at=now - dt.timedelta(minutes=5)).id
        due_early = queries.create_run(s, procedure="d1", bench_name="bench-A", start_at=now - dt.timedelta(hours=1)).id
        future = queries.create_run(s, procedure="f", bench_name="bench-A", start_at=now + dt.timedelta(hours=1)).id
        bench_a = queries.ensure_bench(s, "bench-A").id
    order = []
    for _ in range(5):
        with db.session() as s:
            run = queries.claim_next_run(s, "w", bench_id=bench_a, now=now, config_snapshot={"x": 1})
            order.append(run.id if run is not None else None)
            if run is not None:
                assert run.status == RunStatus.RUNNING.value and run.config_snapshot == {"x": 1}
    assert order == [due_early, due_late, queued_1, queued_2, None]
    with db.session() as s:
        assert queries.get_run(s, future).status == RunStatus.QUEUED.value
        assert queries.get_run(s, other).status == RunStatus.QUEUED.value


def test_checkpoint_steps_events_segments_suspensions(db, run_id):
    with db.session() as s:
        queries.add_steps(s, run_id, [{"name": "soak -40", "kind": "soak", "params": {"t": -40}},
                                      {"name": "record", "kind": "record"}])
        queries.set_step_status(s, run_id, 0, "running", t_bench=10.0)
        queries.set_step_status(s, run_id, 0, "done", t_bench=20.0)
        queries.save_checkpoint(s, run_id, {"step": 1, "state": {"t": 20.0}}, current_step=1, progress=0.5)
        queries.add_event(s, run_id, "info", "step 0 done", t_bench=20.0, data={"n": 1})
        seg = queries.open_segment(s, run_id, "record", 20.0, orientation="ENU", temperature_c=-40.0, repetition=1)
        queries.close_segment(s, seg.id, 30.0)
        queries.begin_suspension(s, run_id, 31.0, "chamber alarm")
        queries.end_suspension(s, run_id, 35.0)
        with pytest.raises(ValueError):
            queries.save_checkpoint(s, run_id, {}, progress=1.5)
        with pytest.raises(ValueError):
            queries.open_segment(s, run_id, "dance", 0.0)
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run.checkpoint == {"step": 1, "state": {"t": 20.0}} and run.current_step == 1 and run.progress == 0.5
        assert [(st.index, st.status, st.started_t, st.finished_t) for st in run.steps] == \
            [(0, "done", 10.0, 20.0), (1, "pending", None, None)]
        assert [(e.kind, e.data) for e in queries.list_events(s, run_id)] == [("info", {"n": 1})]
        assert [(g.orientation, g.t_end) for g in queries.list_segments(s, run_id)] == [("ENU", 30.0)]


def test_fit_versions_count_per_gyro_and_model_and_one_is_accepted(db, run_id):
    def result(channel, c0):
        return {"model": "static", "channel": channel, "coefficients": {"c0": c0}, "stats": {"rms_dph": 0.1}}

    with db.session() as s:
        v1 = queries.save_fits(s, "GYRO-FIT", [run_id], [result("x", 1.0), result("y", 2.0)], accepted=True)
        v2 = queries.save_fits(s, "GYRO-FIT", [run_id], [result("x", 1.5), result("y", 2.5)])
        other = queries.save_fits(s, "GYRO-FIT", [run_id], [{"model": "dynamic", "channel": "x"}])
    assert v1 == {"static": 1} and v2 == {"static": 2} and other == {"dynamic": 1}
    with db.session() as s:
        accepted = queries.list_fits(s, "GYRO-FIT", model="static", accepted_only=True)
        assert [(f.version, f.channel) for f in accepted] == [(1, "x"), (1, "y")]
        assert queries.accept_fits(s, "GYRO-FIT", "static", 2) == 2
        with pytest.raises(StorageError, match="no 'static' fit version 9"):
            queries.accept_fits(s, "GYRO-FIT", "static", 9)
    with db.session() as s:
        accepted = queries.list_fits(s, "GYRO-FIT", model="static", accepted_only=True)
        assert [(f.version, f.coefficients["c0"]) for f in accepted] == [(2, 1.5), (2, 2.5)]
        assert s.query(Fit).filter_by(gyro_id="GYRO-FIT").count() == 5


def test_sampling_summary_reuses_a_recent_summary_only_once_the_run_has_readings(db, run_id):
    """The run page polls the sampling summary, computed at most every ``max_age_s``: a run that has just
    started must not keep showing 0 readings for that long while its data come in."""
    from bench.storage.models import Telemetry
    from bench.storage.sampling import sampling_summary

    assert sampling_summary(db, run_id, max_age_s=60.0)["chamber"]["readings"] == 0
    with db.session() as s:
        s.add_all([Telemetry(run_id=run_id, t=t, device="chamber", chamber_pv=30.0) for t in (0.0, 5.0)])
    first = sampling_summary(db, run_id, max_age_s=60.0)
    assert first["chamber"] == {"readings": 2, "median_interval_s": 5.0, "max_interval_s": 5.0}
    with db.session() as s:
        s.add(Telemetry(run_id=run_id, t=10.0, device="chamber", chamber_pv=30.0))
    assert sampling_summary(db, run_id, max_age_s=60.0)["chamber"]["readings"] == 2     # recent enough: reused
    assert sampling_summary(db, run_id)["chamber"]["readings"] == 3                    # max_age_s 0: counted
