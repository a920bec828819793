"""``runs.live`` is one JSON document that two threads of a ``bench run`` process edit: the engine (status,
outcome, fits) and the heartbeat (progress).  A heartbeat that read the document before the run's final
status and wrote it back after must not erase the outcome (seen under load: ``bench runs show`` said
``outcome: null`` for a run ``bench run`` had reported completed)."""
from __future__ import annotations

import threading

import pytest

import bench.engine.sqlstore as sqlstore
from bench.engine.outcomes import RunOutcome
from bench.engine.sqlstore import SqlRunStore, new_run
from bench.storage import queries


@pytest.mark.parametrize("db", ["sqlite"], indirect=True)
def test_a_heartbeat_between_read_and_write_does_not_erase_the_final_outcome(db, monkeypatch):
    rid = new_run(db, procedure="thermal_ramp", parameters={}, config_snapshot={}, gyro_id="G1", bench_name="b")
    store = SqlRunStore(db)
    store.create_run(str(rid), {"steps": []}, {"steps": []}, 0.0)
    store.set_run_status(str(rid), "running", 0.0)

    has_read, release = threading.Event(), threading.Event()
    real = sqlstore.jsonable

    def held_in_heartbeat(doc):        # the heartbeat has read ``live`` and is about to write it back
        if threading.current_thread().name == "heartbeat" and "progress" in doc:
            has_read.set()
            release.wait(30)
        return real(doc)

    monkeypatch.setattr(sqlstore, "jsonable", held_in_heartbeat)
    beat = threading.Thread(target=store.heartbeat, args=(rid, "me", {"percent": 100.0}), name="heartbeat")
    beat.start()
    assert has_read.wait(30)
    final = threading.Thread(target=store.set_run_status, args=(str(rid), RunOutcome.COMPLETED, 60.0))
    final.start()
    final.join(0.5)          # without one edit at a time, the engine's write lands here, before the heartbeat's
    release.set()
    beat.join(30)
    final.join(30)
    assert not beat.is_alive() and not final.is_alive()

    with db.session() as s:
        run = queries.get_run(s, rid)
        assert run.status == "completed"
        assert run.live.get("outcome") == "completed", run.live
        assert run.live.get("progress") == {"percent": 100.0}


@pytest.mark.parametrize("db", ["sqlite", "postgres"], indirect=True)
def test_a_checkpoint_sets_live_progress_and_keeps_every_other_entry(db):
    rid = new_run(db, procedure="thermal_ramp", parameters={}, config_snapshot={}, gyro_id="G1", bench_name="b")
    store = SqlRunStore(db)
    store.create_run(str(rid), {"steps": [{"kind": "soak", "duration_s": 60.0}]}, {"steps": [{"index": 0, "est_s": 60.0}]}, 0.0)
    store.set_run_status(str(rid), "running", 0.0)
    with db.session() as s:
        before = dict(queries.get_run(s, rid).live)
    progress = {"step_index": 1, "percent": 37.5, "elapsed_bench_s": 22.5, "eta_bench_t": float("inf")}
    store.save_checkpoint(str(rid), {"step_index": 1, "t": 22.5, "progress": progress})
    with db.session() as s:
        run = queries.get_run(s, rid)
        assert run.checkpoint["progress"] == {**progress, "eta_bench_t": None}
        assert run.live == {**before, "progress": {**progress, "eta_bench_t": None}}
        assert run.progress == pytest.approx(0.375) and run.current_step == 1
        run.live = None                       # a row whose live document is empty or JSON null
    store.save_checkpoint(str(rid), {"step_index": 2, "t": 30.0, "progress": {"percent": 50.0}})
    with db.session() as s:
        assert queries.get_run(s, rid).live == {"progress": {"percent": 50.0}}
