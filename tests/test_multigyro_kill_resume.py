"""kill -9 of ``bench run --sim`` recording three simulated gyros in one chamber, in the middle of a
ramp (held at a known bench instant, not after a wall sleep), then ``bench resume``: the parent run and
every gyro's run complete; each gyro's frames committed before the kill are still there unchanged,
no frame index is used twice, and every frame instant between a gyro's first and last frame is either
a stored frame or counted in a recorded gap (0 lost beside the gaps), the kill's outage among them as a
``crash_resume`` gap in bench time.  The outage lasts a stated 120 bench seconds."""
from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

from sqlalchemy import func, select

from bench.storage import queries
from bench.storage.db import open_database
from bench.storage.models import FrameChunk, Gap, Run, Step
from tests.service_support import SAFETY_S, start_held_run
from tests.test_runs_resume import HOLD_T, OUTAGE_S, PARAMS
from tests.test_runs_support import cli, last_json

GYROS = ("K-1", "K-2", "K-3")
RATE_HZ = 1


def _chunks(db, rid):
    with db.session() as s:
        return s.execute(select(FrameChunk.first_index, FrameChunk.count, FrameChunk.raw, FrameChunk.t_first,
                                FrameChunk.t_last).where(FrameChunk.run_id == rid)
                         .order_by(FrameChunk.first_index)).all()


def _unit_runs(db, rid) -> dict[str, int]:
    with db.session() as s:
        return {u.slot: int(u.id) for u in queries.unit_runs(s, rid)}


def _wait_held_mid_ramp(db, rid: int, proc: subprocess.Popen, hold: Path) -> None:
    """Until the run stands at the hold instant inside its ramp, with a checkpoint taken inside the ramp
    and every gyro's frames committed (the bench time does not move meanwhile)."""
    marker = Path(str(hold) + ".held")
    deadline = time.monotonic() + SAFETY_S
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
        if marker.exists() and float(marker.read_text()) == HOLD_T:
            units = _unit_runs(db, rid)
            with db.session() as s:
                ramp = s.scalars(select(Step).where(Step.run_id == rid, Step.kind == "ramp")).first()
                cp = s.get(Run, rid).checkpoint
                frames = [sum(c for (c,) in s.execute(select(FrameChunk.count).where(FrameChunk.run_id == u)))
                          for u in units.values()]
                # the frame writer commits behind the engine (in wall time): held, it catches up
                last = [s.execute(select(func.max(FrameChunk.t_last)).where(FrameChunk.run_id == u)).scalar()
                        for u in units.values()]
            if (ramp is not None and ramp.status == "running" and cp and cp.get("step_index") == ramp.index
                    and (cp.get("step_state") or {}).get("elapsed_s", 0) > 60 and len(frames) == 3
                    and min(frames) > 100 and None not in last and min(last) >= HOLD_T - 30.0):
                return
        time.sleep(0.05)
    raise AssertionError("the run never stood in the middle of its ramp with every gyro's data committed")


def test_kill_a_three_gyro_run_mid_ramp_then_resume(tmp_path):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    args = ["run", "thermal_ramp", *(a for g in GYROS for a in ("--gyro", g)),
            "--sim", "--speed", "200", "--seed", "1", "--data-rate", str(RATE_HZ), "--json", "--no-progress",
            "--db", url]
    for p in PARAMS:
        args += ["--param", p]
    hold = tmp_path / "hold"
    proc, rid = start_held_run(args, tmp_path, hold, HOLD_T)
    db = open_database(url)
    try:
        _wait_held_mid_ramp(db, rid, proc, hold)
        proc.send_signal(signal.SIGKILL)
        proc.wait(SAFETY_S / 10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(SAFETY_S / 10)
    try:
        assert proc.returncode == -signal.SIGKILL
        units = _unit_runs(db, rid)
        assert sorted(units) == ["g1", "g2", "g3"]
        before = {slot: _chunks(db, u) for slot, u in units.items()}
        with db.session() as s:
            # nobody could record the end: the process died
            assert {s.get(Run, u).status for u in (rid, *units.values())} == {"running"}
            t_checkpoint = float(s.get(Run, rid).checkpoint["t"])
        assert t_checkpoint <= HOLD_T

        code, out, err = cli(["resume", str(rid), "--db", url, "--json", "--no-progress", "--outage", str(OUTAGE_S)])
        doc = last_json(out)
        assert code == 0 and doc["status"] == "completed", (doc, err[-3000:])
        assert [(u["slot"], u["gyro_id"], u["status"]) for u in doc["units"]] == [
            ("g1", "K-1", "completed"), ("g2", "K-2", "completed"), ("g3", "K-3", "completed")]

        with db.session() as s:
            parent_gaps = list(s.scalars(select(Gap).where(Gap.run_id == rid)))
            kinds = [e.kind for e in queries.list_events(s, rid)]
            assert s.get(Run, rid).status == "completed"
        assert kinds.count("run_resumed") == 1 and "unit_fault" not in kinds
        (parent_gap,) = parent_gaps            # the parent holds no frames: its outage row counts none
        assert parent_gap.reason == "crash_resume" and parent_gap.frames_missing == 0
        assert parent_gap.t_to - parent_gap.t_from >= OUTAGE_S

        totals = set()
        for slot, unit in units.items():
            after = _chunks(db, unit)
            expected = 0
            for chunk in after:                           # indexes 0..n-1, each exactly once
                assert chunk.first_index == expected, slot
                expected += chunk.count
            n_before = sum(c.count for c in before[slot])
            assert expected > n_before > 100, slot
            raw_before = b"".join(c.raw for c in before[slot])
            assert b"".join(c.raw for c in after)[:len(raw_before)] == raw_before, slot    # unchanged
            with db.session() as s:
                gaps = list(s.scalars(select(Gap).where(Gap.run_id == unit)))
                assert s.get(Run, unit).status == "completed"
            (crash,) = [g for g in gaps if g.reason == "crash_resume"]
            last_before = max(c.t_last for c in before[slot])
            # the outage in bench time: from the gyro's last frame before the kill to its first after the
            # bench came back at the checkpoint's instant and the stated outage passed
            assert crash.t_from == last_before and HOLD_T - 30.0 <= last_before <= HOLD_T, slot
            assert t_checkpoint + OUTAGE_S <= crash.t_to <= t_checkpoint + OUTAGE_S + 2.0 / RATE_HZ, slot
            assert crash.frames_missing is not None and crash.frames_missing > 0, slot
            assert not any(after[k].t_first < crash.t_to < after[k].t_last for k in range(len(after))), slot
            # 0 lost beside the gaps: every frame instant from the first frame to the last is accounted for
            span = round((after[-1].t_last - after[0].t_first) * RATE_HZ) + 1
            missing = sum(g.frames_missing or 0 for g in gaps)
            assert expected + missing == span, (slot, expected, missing, span, [(g.reason, g.frames_missing) for g in gaps])
            totals.add((crash.t_to, after[-1].t_last))
        # after the resume the three gyros recorded the same instants (before the kill each had committed
        # what its own frame writer had flushed, so their counts may differ by a few frames)
        assert len(totals) == 1, totals
    finally:
        db.dispose()
