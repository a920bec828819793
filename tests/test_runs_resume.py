"""kill -9 of ``bench run --sim`` in the middle of a ramp, then ``bench resume``: the run completes,
every frame committed before the kill is still there unchanged, no frame index is used twice, and
the interruption is a recorded gap."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from sqlalchemy import select

from bench.storage.db import open_database
from bench.storage.models import FrameChunk, Gap, Run, Segment, Step
from tests.test_runs_support import cli, last_json

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ["start_c=30", "soak_h=0.02", "warmup_min=1", "rate_c_per_min=1", "end_c=18", "final_hold_min=1"]


def _chunks(db, rid):
    with db.session() as s:
        return s.execute(select(FrameChunk.first_index, FrameChunk.count, FrameChunk.raw)
                         .where(FrameChunk.run_id == rid).order_by(FrameChunk.first_index)).all()


def _wait_mid_ramp(db, rid: int, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Until a checkpoint taken inside the ramp step is stored (and frames are committed)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
        with db.session() as s:
            run = s.get(Run, rid)
            ramp = s.scalars(select(Step).where(Step.run_id == rid, Step.kind == "ramp")).first()
            cp = run.checkpoint if run is not None else None
        if (ramp is not None and ramp.status == "running" and cp and cp.get("step_index") == ramp.index
                and cp.get("step_state") and cp["step_state"].get("elapsed_s", 0) > 60):
            return
        time.sleep(0.05)
    raise AssertionError("the run never reached the middle of its ramp")


def test_kill_mid_ramp_then_resume(tmp_path):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    args = [sys.executable, "-m", "bench.cli", "run", "thermal_ramp", "--gyro", "K1", "--sim", "--speed", "200",
            "--data-rate", "1", "--json", "--no-progress", "--db", url]
    for p in PARAMS:
        args += ["--param", p]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        first = proc.stdout.readline().decode()
        assert first.startswith("run "), (first, proc.stderr.read().decode()[-3000:] if proc.poll() else "")
        rid = int(first.split()[1])
        db = open_database(url)
        _wait_mid_ramp(db, rid, proc)
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

    code, out, err = cli(["resume", str(rid), "--db", url, "--json", "--no-progress"])
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
    code, out, _ = cli(["runs", "show", str(rid), "--json", "--db", url])
    show = json.loads(out)
    assert show["status"] == "completed" and any(g["reason"] == "crash_resume" for g in show["gaps"])
    # a finished run cannot be resumed again
    code, _, err = cli(["resume", str(rid), "--db", url])
    assert code == 2 and "already ended" in err
    db.dispose()
