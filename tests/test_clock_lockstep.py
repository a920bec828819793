"""``bench.clock.LockstepClock``: time moves only when driven, each instant is served then received
before ``sleep`` returns, holds stop the driving thread at a known bench instant, the pace is a limit."""
from __future__ import annotations

import threading
import time

import pytest

from bench.clock import LockstepClock, clock_from_json, parse_speed

T0 = 1_767_225_600.0


def test_each_instant_is_served_then_received_before_time_moves_on():
    clock = LockstepClock(T0, None)
    log = []
    clock.serve("dev", lambda t: log.append(("serve", t)) or {"n": len(log)})
    clock.receive("drv", lambda t, reports: log.append(("receive", t, reports["dev"]["n"])))
    assert clock.now() == T0
    clock.sleep(2.0)
    clock.advance_to(T0 + 5.0)
    assert log == [("serve", T0 + 2), ("receive", T0 + 2, 1), ("serve", T0 + 5), ("receive", T0 + 5, 3)]
    clock.advance_to(T0 + 1.0)                      # never backwards
    assert clock.now() == T0 + 5.0 and len(log) == 4


def test_hold_stops_the_driver_at_the_instant_until_released():
    clock = LockstepClock(T0, None)
    clock.hold_at(T0 + 10.0)
    done = threading.Event()
    driver = threading.Thread(target=lambda: (clock.advance_to(T0 + 100.0), done.set()), daemon=True)
    driver.start()
    assert clock.wait_held(10.0)
    assert clock.now() == T0 + 10.0 and not done.is_set()
    clock.release()
    assert done.wait(10.0) and clock.now() == T0 + 100.0


def test_a_hold_moved_while_held_lets_the_driver_go_on_to_the_new_instant():
    clock = LockstepClock(T0, None)
    clock.hold_at(T0 + 10.0)
    driver = threading.Thread(target=lambda: clock.advance_to(T0 + 100.0), daemon=True)
    driver.start()
    assert clock.wait_held(10.0) and clock.now() == T0 + 10.0
    clock.hold_at(T0 + 10.0)                        # the same instant again: still held there
    assert clock.held and clock.wait_held(0.0)
    clock.hold_at(T0 + 40.0)                        # moved: the driver goes on and stands at the new one
    assert clock.wait_held(10.0) and clock.now() == T0 + 40.0
    clock.release()
    driver.join(10)
    assert not driver.is_alive() and clock.now() == T0 + 100.0


def test_hold_file_across_processes(tmp_path):
    hold = tmp_path / "hold"
    hold.write_text(repr(T0 + 4.0))
    clock = clock_from_json(LockstepClock(T0, None, hold_file=str(hold)).to_json())
    driver = threading.Thread(target=lambda: clock.advance_to(T0 + 8.0), daemon=True)
    driver.start()
    marker = tmp_path / "hold.held"
    deadline = time.monotonic() + 10
    while not (marker.exists() and float(marker.read_text()) == T0 + 4.0):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert clock.now() == T0 + 4.0
    hold.unlink()
    driver.join(10)
    assert clock.now() == T0 + 8.0


def test_pace_is_an_upper_limit_on_speed():
    clock = LockstepClock(T0, 1000.0)
    w0 = time.monotonic()
    for _ in range(100):
        clock.sleep(5.0)                             # 500 bench s at most x1000: >= 0.5 s wall
    assert time.monotonic() - w0 >= 0.5 - LockstepClock.BURST_WALL_S


def test_parse_speed():
    assert parse_speed("max") is None and parse_speed("600") == 600.0
    for bad in ("0", "-3", "fast", "inf"):
        with pytest.raises(ValueError, match="--speed"):
            parse_speed(bad)


def test_work_done_at_an_instant_is_not_lost_pace(monkeypatch):
    """At x1 with 2-s instants whose serving takes 0.6 s of wall (more than the catching-up
    allowance), the clock still keeps x1: the next instant is due one step after this one's due
    time, not one step after its work ended.  A fake wall clock makes this exact."""
    import bench.clock as bc

    wall = [100.0]
    monkeypatch.setattr(bc.time, "monotonic", lambda: wall[0])
    monkeypatch.setattr(bc.time, "sleep", lambda s: wall.__setitem__(0, wall[0] + s))
    clock = LockstepClock(T0, 1.0)

    def busy(t):
        wall[0] += 0.6                               # the serving work at this instant
        return {}

    clock.serve("gyro", busy)
    w0 = wall[0]
    for _ in range(30):
        clock.sleep(2.0)
    assert wall[0] - w0 == pytest.approx(60.0 + 0.6, abs=1e-6)     # was 30 x 2.35 s: x0.85


def test_a_stall_longer_than_the_allowance_is_forgotten(monkeypatch):
    """After a 10-s stall the clock does not race to make it up: two instants k steps apart are
    served at least k steps - BURST_WALL_S of wall apart."""
    import bench.clock as bc

    wall = [100.0]
    monkeypatch.setattr(bc.time, "monotonic", lambda: wall[0])
    monkeypatch.setattr(bc.time, "sleep", lambda s: wall.__setitem__(0, wall[0] + s))
    clock = LockstepClock(T0, 1.0)
    served: list[float] = []
    clock.serve("probe", lambda t: served.append(wall[0]) or {})
    clock.sleep(1.0)
    wall[0] += 10.0                                  # the host stalled 10 s
    for _ in range(5):
        clock.sleep(1.0)
    after = served[1:]                               # the instants after the stall
    assert after[0] == pytest.approx(111.0)          # the late instant is served at once
    for j in range(len(after)):
        for k in range(j + 1, len(after)):
            assert after[k] - after[j] >= (k - j) - LockstepClock.BURST_WALL_S - 1e-9
    assert after[-1] - after[0] == pytest.approx(4.0 - LockstepClock.BURST_WALL_S)
