"""kill -9 of ``bench run --sim`` in the middle of a ramp, then ``bench resume``: the run completes,
every frame committed before the kill is still there unchanged, no frame index is used twice, the
interruption is a recorded gap, and the simulated bench continues from its checkpointed physical
state: chamber and probe temperatures do not jump across the outage (which lasts a stated 120 bench
seconds, so nothing here depends on how long the host took to restart)."""
from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

from sqlalchemy import func, select

from bench.storage.db import open_database
from bench.storage.models import FrameChunk, Gap, ProbeReadingRow, Run, Segment, Step, Telemetry
from tests.service_support import start_held_run
from tests.test_runs_support import cli, last_json

OUTAGE_S = 120.0
T0 = 1_767_225_600.0            # a seeded simulated bench starts at this bench instant
HOLD_T = T0 + 500.0             # the ramp runs from about T0 + 132 s to T0 + 852 s
TELEMETRY_LAG_S = 30.0          # the chamber is polled every few bench seconds
PARAMS = ["start_c=30", "soak_h=0.02", "warmup_min=1", "rate_c_per_min=1", "end_c=42", "final_hold_min=1"]


def _chunks(db, rid):
    with db.session() as s:
        return s.execute(select(FrameChunk.first_index, FrameChunk.count, FrameChunk.raw)
                         .where(FrameChunk.run_id == rid).order_by(FrameChunk.first_index)).all()


def _wait_held_mid_ramp(db, rid: int, proc: subprocess.Popen, hold: Path, timeout_s: float = 120.0) -> None:
    """Until the run stands at the hold instant inside its ramp, with a checkpoint taken inside the
    ramp stored and frames and the chamber's telemetry up to the hold committed (the bench time does not
    move meanwhile; telemetry rows commit on the wall clock, later than the frames on a loaded machine)."""
    marker = Path(str(hold) + ".held")
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
        if marker.exists() and float(marker.read_text()) == HOLD_T:
            with db.session() as s:
                run = s.get(Run, rid)
                ramp = s.scalars(select(Step).where(Step.run_id == rid, Step.kind == "ramp")).first()
                cp = run.checkpoint if run is not None else None
                frames = sum(c.count for c in s.execute(select(FrameChunk.count).where(FrameChunk.run_id == rid)))
                last_pv_t = s.scalar(select(func.max(Telemetry.t)).where(
                    Telemetry.run_id == rid, Telemetry.device == "chamber"))
            if (ramp is not None and ramp.status == "running" and cp and cp.get("step_index") == ramp.index
                    and cp.get("step_state") and cp["step_state"].get("elapsed_s", 0) > 60 and frames > 100
                    and last_pv_t is not None and last_pv_t >= HOLD_T - TELEMETRY_LAG_S):
                return
        time.sleep(0.05)
    raise AssertionError("the run never stood in the middle of its ramp with its data committed")


def _assert_continuous(db, rid: int, gap) -> None:
    """Across the outage the chamber's own ramp goes on (1 C/min: 2 C in 120 s, plus the air catching
    up with its set point), and the probes on the gyro, with their thermal lag, move less: no jump back
    to room temperature (23 C) or to a fresh chamber."""
    with db.session() as s:
        pv = s.execute(select(Telemetry.t, Telemetry.chamber_pv).where(
            Telemetry.run_id == rid, Telemetry.device == "chamber").order_by(Telemetry.t)).all()
        probes = s.execute(select(ProbeReadingRow.t, ProbeReadingRow.celsius).where(
            ProbeReadingRow.run_id == rid, ProbeReadingRow.name == "t1").order_by(ProbeReadingRow.t)).all()
    for what, rows, tol in (("chamber PV", pv, 5.0), ("probe t1", probes, 3.0)):
        before = [v for t, v in rows if t <= gap.t_from]
        after = [v for t, v in rows if t >= gap.t_to]
        assert before and after, what
        assert abs(after[0] - before[-1]) < tol, (what, before[-3:], after[:3])
        assert 25.0 < after[0] < 42.5, (what, after[0])        # warmer than the room, below the ramp's end


def test_kill_mid_ramp_then_resume(tmp_path):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    args = ["run", "thermal_ramp", "--gyro", "K1", "--sim", "--speed", "200",
            "--seed", "1", "--data-rate", "1", "--json", "--no-progress", "--db", url]
    for p in PARAMS:
        args += ["--param", p]
    hold = tmp_path / "hold"
    proc, rid = start_held_run(args, tmp_path, hold, HOLD_T)
    try:
        db = open_database(url)
        _wait_held_mid_ramp(db, rid, proc, hold)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    before = _chunks(db, rid)
    n_before = sum(c.count for c in before)
    assert n_before > 100
    with db.session() as s:
        status_after_kill = s.get(Run, rid).status
    assert status_after_kill == "running"       # nobody could record the end: the process died

    code, out, err = cli(["resume", str(rid), "--db", url, "--json", "--no-progress", "--outage", str(OUTAGE_S)])
    doc = last_json(out)
    assert code == 0 and doc["status"] == "completed", (doc, err[-3000:])

    after = _chunks(db, rid)
    expected = 0
    for first_index, count, _ in after:            # indexes 0..n-1, each exactly once
        assert first_index == expected
        expected += count
    assert expected == doc["frames"] > n_before
    assert b"".join(c.raw for c in before) == b"".join(c.raw for c in after)[:len(b"".join(c.raw for c in before))]
    with db.session() as s:
        gaps = list(s.scalars(select(Gap).where(Gap.run_id == rid)))
        segs = list(s.scalars(select(Segment).where(Segment.run_id == rid).order_by(Segment.t_start)))
        steps = list(s.scalars(select(Step).where(Step.run_id == rid).order_by(Step.index)))
        last_t_before = max(c.t_last for c in s.execute(select(FrameChunk.t_last).where(
            FrameChunk.run_id == rid, FrameChunk.first_index < n_before)).all())
    interrupted = [g for g in gaps if g.reason == "crash_resume"]       # one row for the crash, counted
    assert len(interrupted) == 1 and interrupted[0].frames_missing is not None and interrupted[0].t_to > interrupted[0].t_from >= last_t_before - 1e-6
    assert all(st.status == "done" for st in steps[:-1])
    ramp_pieces = [sg for sg in segs if sg.labels["phase"] == "ramp"]
    assert len(ramp_pieces) == 2 and [p.labels["piece"] for p in ramp_pieces] == [0, 1]
    # the outage lasts from the last frame before the crash to the first one after the resume
    assert interrupted[0].t_from <= ramp_pieces[1].t_start <= interrupted[0].t_to
    _assert_continuous(db, rid, interrupted[0])
    code, out, _ = cli(["runs", "show", str(rid), "--json", "--db", url])
    show = json.loads(out)
    assert show["status"] == "completed" and any(g["reason"] == "crash_resume" for g in show["gaps"])
    # a finished run cannot be resumed again
    code, _, err = cli(["resume", str(rid), "--db", url])
    assert code == 2 and "already ended" in err
    db.dispose()
