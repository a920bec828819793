"""Several gyros in one chamber (issue 16): the bench config's gyro slots, the multi-channel supply,
the simulated bench with N units, and the two acceptance runs: three gyros in one run, each with its
own data and coefficients by its ID; one gyro's line dropping mid-run (by bench time) while the
other two complete."""
from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from api.app import create_app
from bench.config import BenchConfig, GyroConfig, GyroSlot, ProbeConfig, PsuConfig, SlotPower
from bench.devices.psu import PsuChannel, PsuCommandError, ScpiPowerSupply
from bench.errors import ProtocolError
from bench.engine import Engine, EngineConfig
from bench.engine.factory import build_devices, close_devices, engine_config_for, make_fit_hook
from bench.engine.sqlstore import SqlRunStore, new_run, run_report
from bench.sim.bench import lockstep_clock
from bench.sim.multibench import MultiGyroBench, unit_scenario
from bench.sim.psu import MultiChannelPsuSimulator, PsuModel
from bench.sim.scenario import Scenario
from bench.storage import open_database, queries
from bench.storage.export import run_dataset
from tests.api_support import VIEWER, TOKENS
from tests.test_runs_support import cli

SHORT = {"points_c": [20, 25, 30, 35], "soak_h": 0.04, "record_min": 0.5}


def _slot(name: str, url: str, serial: str, **power) -> dict:
    return {"slot": name, "gyro": {"url": url, "channel_probes": {"x": "t1"}},
            "probes": {"probes": {"t1": serial}}, "power": power or {"channel": int(name[1:])}}


# ---- config ---------------------------------------------------------------------------------------
def test_single_gyro_config_unchanged_and_slots_validated():
    single = BenchConfig()
    assert not single.multi and single.gyros == [] and single.unit_faults == "continue"
    ok = BenchConfig.model_validate({"gyros": [_slot("g1", "socket://h:1", "000000000001"),
                                               _slot("g2", "socket://h:2", "000000000002",
                                                     psu={"url": "socket://h:9"}, voltage_v=12)]})
    assert ok.multi and [s.slot for s in ok.gyros] == ["g1", "g2"]
    assert ok.slot("g2").power.psu.url == "socket://h:9" and ok.slot("g2").power.channel is None
    bad = [
        ([_slot("g1", "socket://h:1", "000000000001"), _slot("g1", "socket://h:2", "000000000002")],
         r"gyros.1: slot 'g1' is already used by slot 'g1'"),
        ([_slot("g1", "socket://h:1", "000000000001"), _slot("g2", "socket://h:1", "000000000002")],
         r"gyros.1: gyro.url 'socket://h:1' is already used by slot 'g1'"),
        ([_slot("g1", "socket://h:1", "000000000001"), _slot("g2", "socket://h:2", "000000000001")],
         r"gyros.1: probe serial '000000000001' is already used"),
        ([_slot("g1", "socket://h:1", "000000000001", channel=1, psu={"url": "x"})],
         r"exactly one of channel .* / psu"),
        ([{**_slot("g1", "socket://h:1", "000000000001"), "gyro": {"channel_probes": {"x": "t9"}}}],
         r"gyros.0.gyro.channel_probes.x: 't9' is not a configured probe"),
    ]
    for gyros, match in bad:
        with pytest.raises(ValidationError, match=match):
            BenchConfig.model_validate({"gyros": gyros})


def test_example_fixture_config_builds_a_fixture():
    from pathlib import Path

    from bench.clock import RealClock

    cfg = BenchConfig.load(Path(__file__).resolve().parents[1] / "examples" / "bench-multi.json")
    devices = build_devices(cfg, RealClock())      # drivers open nothing until used
    try:
        assert [u.slot for u in devices.units] == ["s1", "s2", "s3", "s4"]
        kinds = [type(u.psu).__name__ for u in devices.units]
        assert kinds == ["PsuChannel", "PsuChannel", "PsuChannel", "ScpiPowerSupply"]
        assert [u.psu.channel for u in devices.units[:3]] == [1, 2, 3] and len(devices.shared) == 1
        assert [u.gyro.lockstep_name for u in devices.units] == ["gyro:s1", "gyro:s2", "gyro:s3", "gyro:s4"]
        assert devices.only(["s2", "s4"]).units[1].slot == "s4"
        with pytest.raises(ValueError, match="no gyro slot s9"):
            devices.only(["s9"])
    finally:
        close_devices(devices)


def test_assign_gyros_to_slots():
    cfg = BenchConfig.model_validate({"gyros": [_slot(f"g{k}", f"socket://h:{k}", f"00000000000{k}")
                                                for k in (1, 2, 3)]})
    assert cfg.assign_gyros(["A", "B"]) == [("g1", "A"), ("g2", "B")]
    assert cfg.assign_gyros(["g2=A", "B"]) == [("g1", "B"), ("g2", "A")]
    with pytest.raises(ValueError, match="4 gyros named but the bench has 3 slots"):
        cfg.assign_gyros(["A", "B", "C", "D"])
    with pytest.raises(ValueError, match="named twice"):
        cfg.assign_gyros(["A", "A"])
    with pytest.raises(KeyError, match="no gyro slot 'g7'"):
        cfg.assign_gyros(["g7=A"])
    with pytest.raises(ValueError, match="carries one gyro"):
        BenchConfig().assign_gyros(["A"])


# ---- the multi-channel supply ---------------------------------------------------------------------
def test_psu_channels_over_one_line():
    models = [PsuModel(), PsuModel(), PsuModel()]
    sim = MultiChannelPsuSimulator(models, lockstep_clock(None, 1))
    sim.start()
    supply = ScpiPowerSupply(PsuConfig(url=sim.url))
    try:
        lock = threading.Lock()
        ch = {n: PsuChannel(supply, n, lock) for n in (1, 2, 3)}
        ch[2].set_voltage(12.5)
        ch[3].set_voltage(28.0)
        ch[3].output(True)
        assert [m.output_on for m in models] == [False, False, True]
        assert models[1].voltage_setting == pytest.approx(12.5) and models[0].voltage_setting != pytest.approx(12.5)
        assert ch[3].output_state() and not ch[1].output_state()
        assert ch[3].measure_voltage() == pytest.approx(28.0, abs=0.1) and ch[3].measure_current() > 0
        assert ch[2].measure_current() == 0
        volts, amps, on = ch[3].reading()                  # one program message, three answers
        assert volts == pytest.approx(28.0, abs=0.1) and amps == pytest.approx(ch[3].measure_current()) and on
        assert ch[1].reading()[2] is False
        with pytest.raises(PsuCommandError, match=r"-222"):
            PsuChannel(supply, 4, lock).output(True)
        # every channel in one program message: the same answers as one channel at a time
        requests = len(sim.received.entries())
        assert supply.channel_readings([1, 2, 3]) == [ch[n].reading() for n in (1, 2, 3)]
        assert len(sim.received.entries()) == requests + 1 + 3
        # channel 4 does not exist: its INST:NSEL is refused, the echo shows channel 2 still selected
        with pytest.raises(ProtocolError, match=r"channel 4 reading '2;"):
            supply.channel_readings([2, 4])
    finally:
        supply.close()
        sim.stop()


# ---- simulated units -------------------------------------------------------------------------------
def test_unit_scenarios_seeded_different_and_hidden_effect_on_one_unit():
    base = Scenario.builtin("default").with_changes(seed=7)
    a = [unit_scenario(base, k) for k in range(3)]
    assert a == [unit_scenario(base, k) for k in range(3)]           # deterministic by seed
    intercepts = {round(s.bias["x"].intercept_dph, 9) for s in a}
    assert len(intercepts) == 3 and len({s.seed for s in a}) == 3
    assert unit_scenario(base.with_changes(seed=8), 0).bias["x"] != a[0].bias["x"]
    warm = {"warmup": {"tau_s": 600.0, "amplitude_dph": {"x": 0.5}}}
    hidden = unit_scenario(base, 1, effects=warm)
    assert hidden.effects.warmup is not None and a[1].effects.warmup is None
    assert hidden.bias == a[1].bias                                  # only the effect differs
    with pytest.raises(ValueError, match="unknown effect"):
        unit_scenario(base, 1, effects={"magic": {}})
    with pytest.raises(ValueError, match="no slot g9"):
        MultiGyroBench(units=2, clock=lockstep_clock(None, 7), unit_effects={"g9": warm})


# ---- acceptance (a): three gyros, one run --------------------------------------------------------------
def test_three_gyros_one_run_each_own_data_and_coefficients(tmp_path):
    url = f"sqlite:///{tmp_path / 'multi.sqlite'}"
    args = ["run", "eight_position", "--gyro", "U-A", "--gyro", "U-B", "--gyro", "g3=U-C", "--sim",
            "--speed", "max", "--seed", "5", "--json", "--no-progress", "--db", url]
    for key, value in SHORT.items():
        args += ["--param", f"{key}={json.dumps(value)}"]
    code, out, err = cli(args)
    doc = json.loads(out)
    assert code == 0 and doc["status"] == "completed", err[-3000:]
    units = {u["slot"]: u for u in doc["units"]}
    assert [(s, units[s]["gyro_id"]) for s in sorted(units)] == [("g1", "U-A"), ("g2", "U-B"), ("g3", "U-C")]
    assert doc["frames"] == 0                       # the parent run holds the plan and the chamber, no frames
    assert all(u["status"] == "completed" and u["gaps"] == [] for u in units.values())
    assert len({u["frames"] for u in units.values()}) == 1 and units["g1"]["frames"] > 1000

    truth = MultiGyroBench(units=3, clock=lockstep_clock(None, 5), seed=5).truth()
    db = open_database(url)
    try:
        means = {}
        for slot, unit in units.items():
            ds = run_dataset(unit["run_id"], db, latitude_deg=45.75)
            assert len(ds) > 500
            means[slot] = np.array([np.nanmean(ds[f"gyro_{c}"]) for c in "xyz"])
            with db.session() as s:
                run = queries.get_run(s, unit["run_id"])
                assert run.parent_id == doc["run_id"] and run.slot == slot and run.gyro_id == unit["gyro_id"]
        assert not np.allclose(means["g1"], means["g2"]) and not np.allclose(means["g2"], means["g3"])
    finally:
        db.dispose()

    client = TestClient(create_app(open_database(url), tokens=TOKENS))
    try:
        fitted = {}
        for slot, unit in units.items():
            r = client.get(f"/gyros/{unit['gyro_id']}/coefficients", headers=VIEWER)
            assert r.status_code == 200, r.text
            model = r.json()["models"][0]
            assert model["model"] == "static"
            fitted[slot] = {c: model["channels"][c]["coefficients"]["A0"] for c in "xyz"}
        # each gyro's intercepts are its own unit's (seeded variation of 0.5 deg/h), not a neighbour's
        for slot in units:
            for c in "xyz":
                own = truth[slot]["channels"][c]["intercept_dph"]
                assert fitted[slot][c] == pytest.approx(own, abs=0.08), (slot, c, fitted, truth)
        assert len({tuple(f.values()) for f in fitted.values()}) == 3
        parent = client.get(f"/runs/{doc['run_id']}", headers=VIEWER).json()
        assert [(u["slot"], u["status"]) for u in parent["units"]] == [("g1", "completed"), ("g2", "completed"),
                                                                       ("g3", "completed")]
    finally:
        client.close()


# ---- acceptance (b): one line drops mid-run --------------------------------------------------------------
def _engine_run(db, bench, clock, cfg, ec, drop_at_s=None):
    import procedures

    module = procedures.get("eight_position")
    params = module.Params.model_validate({**SHORT, "positions": ["ENU", "WSU"]})
    run_id = new_run(db, procedure=module.NAME, parameters=params.model_dump(mode="json"),
                     config_snapshot=cfg.model_dump(mode="json"), gyro_id=None, bench_name=cfg.name,
                     units=cfg.assign_gyros(["D-1", "D-2", "D-3"]))
    if drop_at_s is not None:
        bench.drop_line("g2", clock.now() + drop_at_s)
    store = SqlRunStore(db, geometry=cfg.turntable.geometry)
    devices = build_devices(cfg, clock)
    engine = Engine(devices, store, clock, cfg, engine_config=ec,
                    fit_hook=make_fit_hook(db, store, latitude_deg=cfg.latitude_deg))
    t0 = clock.now()
    try:
        status = engine.run(str(run_id), module.build(params))
    finally:
        store.close(run_id)
        close_devices(devices)
    return run_id, status, t0


def test_one_line_drops_mid_run_others_complete(db):
    clock = lockstep_clock(None, 11)
    bench = MultiGyroBench(units=3, clock=clock, seed=11).start()
    try:
        cfg = bench.bench_config()
        run_id, status, t0 = _engine_run(db, bench, clock, cfg, engine_config_for(clock), drop_at_s=300.0)
    finally:
        bench.stop()
    assert status == "completed"
    report = run_report(db, run_id)
    assert report["status"] == "completed" and report["suspensions"] == []
    assert "1 of 3 gyro units failed: g2: gyro frames stopped" in report["status_reason"]
    units = {u["slot"]: u for u in report["units"]}
    assert units["g1"]["status"] == units["g3"]["status"] == "completed"
    assert units["g1"]["gaps"] == units["g3"]["gaps"] == []
    assert units["g2"]["status"] == "failed" and "gyro frames stopped" in units["g2"]["error"]
    (gap,) = units["g2"]["gaps"]
    # the gap starts at g2's last frame (the line dropped at bench time t0 + 300 s) and runs to the end
    assert gap["t_from"] == pytest.approx(t0 + 300.0, abs=2.0) and gap["reason"].startswith("unit fault")
    with db.session() as s:
        end = queries.get_run(s, units["g2"]["run_id"]).live["status_t"]
        events = [e.kind for e in queries.list_events(s, run_id)] if hasattr(queries, "list_events") else None
    assert gap["t_to"] == pytest.approx(end)
    assert units["g2"]["frames"] < 0.8 * units["g1"]["frames"] and units["g1"]["frames"] == units["g3"]["frames"]
    # the procedure's fits ran per gyro: the two complete units have their coefficients
    fit = next(iter(report["fits"].values()))
    assert "units" in fit, report["fits"]
    assert fit["units"]["g1"]["status"] == fit["units"]["g3"]["status"] == "done"
    assert fit["units"]["g1"]["gyro_id"] == "D-1" and fit["units"]["g3"]["gyro_id"] == "D-3"
    assert events.count("unit_fault") == 1


def test_unit_fault_policy_suspend_suspends_the_whole_run(db):
    clock = lockstep_clock(None, 12)
    bench = MultiGyroBench(units=3, clock=clock, seed=12).start()
    try:
        cfg = bench.bench_config().model_copy(update={"unit_faults": "suspend"})
        ec = engine_config_for(clock).model_copy(update={"suspension_cap_s": 600.0})
        run_id, status, t0 = _engine_run(db, bench, clock, cfg, ec, drop_at_s=300.0)
    finally:
        bench.stop()
    assert status == "aborted"
    report = run_report(db, run_id)
    (susp,) = report["suspensions"]
    assert susp["reason"].startswith("g2: gyro frames stopped") and susp["t_from"] == pytest.approx(t0 + 312, abs=4)
    assert "suspended for a total" in report["error"]


# ---- the operator service: POST /runs with gyro_ids, executed by the bench worker ----------------------
def test_api_queues_gyro_ids_and_the_worker_runs_them(tmp_path):
    from bench.worker import Worker
    from tests.api_support import OPERATOR, wait_for

    db = open_database(f"sqlite:///{tmp_path / 'svc.sqlite'}")
    clock = lockstep_clock(None, 13)
    bench = MultiGyroBench(units=2, clock=clock, seed=13).start()
    cfg = bench.bench_config().model_copy(update={"name": "fixture1"})
    worker = Worker(db, "fixture1", cfg, None, clock, bench_state=bench, heartbeat_s=0.2, stale_after_s=5.0,
                    poll_s=0.05, run_jobs=False)
    client = TestClient(create_app(db, tokens=TOKENS))
    try:
        body = {"procedure": "thermal_ramp", "bench": "fixture1", "gyro_ids": ["W-1", "g2=W-2"],
                "params": {"start_c": 26, "soak_h": 0.04, "warmup_min": 1, "rate_c_per_min": 2, "end_c": 22,
                           "final_hold_min": 1}}
        bad = client.post("/runs", json={**body, "gyro_id": "W-0"}, headers=OPERATOR)
        assert bad.status_code == 422 and "exactly one of gyro_id" in bad.text
        too_many = client.post("/runs", json={**body, "gyro_ids": ["A", "B", "C"]}, headers=OPERATOR)
        assert too_many.status_code == 422 and "3 gyros named but the bench has 2 slots" in too_many.text
        r = client.post("/runs", json=body, headers=OPERATOR)
        assert r.status_code == 201, r.text
        run_id = r.json()["id"]
        queued = client.get(f"/runs/{run_id}", headers=VIEWER).json()
        assert [(u["slot"], u["gyro_id"], u["status"]) for u in queued["units"]] == [
            ("g1", "W-1", "queued"), ("g2", "W-2", "queued")]
        assert worker.run_once() == run_id                 # the parent is claimed, never a child on its own
        assert worker.run_once() is None
        done = client.get(f"/runs/{run_id}", headers=VIEWER).json()
        assert done["status"] == "completed", done.get("error")
        assert [(u["slot"], u["status"]) for u in done["units"]] == [("g1", "completed"), ("g2", "completed")]
        # the parent's sampling lists each gyro's probes and frames (it stores none of its own)
        assert done["sampling"]["probes"]["readings"] == 0 and done["sampling"]["chamber"]["readings"] > 0
        assert sorted(done["sampling"]["units"]) == ["g1", "g2"]
        for slot, unit_sampling in done["sampling"]["units"].items():
            assert unit_sampling["gyro"]["readings"] > 100, slot
            assert unit_sampling["probes"]["max_interval_s"] <= 2.0, slot
        for u in done["units"]:
            unit = client.get(f"/runs/{u['run_id']}", headers=VIEWER).json()
            assert unit["parent_id"] == run_id and unit["gyro_id"] == u["gyro_id"]
            assert unit["latest"]["gyro"]["frames"] > 100 and unit["sampling"]["probes"]["max_interval_s"] <= 2.0
            data = client.get(f"/runs/{u['run_id']}/data?stream=seconds&format=json", headers=VIEWER).json()
            assert len(data["columns"]["gyro_x"]) > 100
        by_gyro = client.get("/runs?gyro_id=W-2", headers=VIEWER).json()["runs"]
        assert [r["slot"] for r in by_gyro] == ["g2"]      # the gyro's runs: its own, as before
    finally:
        client.close()
        bench.stop()
        db.dispose()


def test_a_slot_mounted_turned_sees_its_own_positions():
    from bench.devices.orientation import EIGHT_POSITION_GEOMETRY as geo
    from bench.engine.fixture import slot_position
    from procedures.eight_position import EIGHT_POSITIONS

    same = [slot_position(p, geo, geo.model_copy(update={"mounting": geo.mounting})) for p in EIGHT_POSITIONS]
    assert same == list(EIGHT_POSITIONS)
    # turned 180 degrees about its z axis: its x and y point the opposite way in every position
    flip = {"E": "W", "W": "E", "N": "S", "S": "N", "U": "D", "D": "U"}
    turned = [slot_position(p, geo, geo.model_copy(update={"mounting": "WSU"})) for p in EIGHT_POSITIONS]
    assert turned == [flip[p[0]] + flip[p[1]] + p[2] for p in EIGHT_POSITIONS]


# ---- a unit's own supply unreachable: that unit's fault, not the whole power step ------------------------
def _plan_run(db, bench, clock, cfg, ec, plan, gyro_ids=("P-1", "P-2", "P-3")):
    """Run ``plan`` on the simulated fixture; returns (run id, status, bench time at the start)."""
    run_id = new_run(db, procedure=plan.name, parameters={}, config_snapshot=cfg.model_dump(mode="json"),
                     gyro_id=None, bench_name=cfg.name, units=cfg.assign_gyros(list(gyro_ids)))
    store = SqlRunStore(db, geometry=cfg.turntable.geometry)
    devices = build_devices(cfg, clock)
    engine = Engine(devices, store, clock, cfg, engine_config=ec)
    t0 = clock.now()
    try:
        status = engine.run(str(run_id), plan)
    finally:
        store.close(run_id)
        close_devices(devices)
    return run_id, status, t0


def _power_plan():
    from bench.engine.steps import GyroPower, Plan, Record

    return Plan(name="power", steps=[GyroPower(on=True), Record(duration_s=120.0, labels={"p": 1})])


def _events(db, run_id):
    with db.session() as s:
        return [(e.kind, e.message) for e in queries.list_events(s, run_id)]


def test_own_supply_unreachable_marks_only_its_unit_under_continue(tmp_path):
    """g2's own supply refuses connections from the start to bench time +60 s: the power step goes on
    for g1 and g3; g2 is marked faulted, its power is sent again once its supply answers, its outage
    is a gap of its run, and every unit's run completes."""
    db = open_database(f"sqlite:///{tmp_path / 'psu.sqlite'}")
    clock = lockstep_clock(None, 21)
    bench = MultiGyroBench(units=3, clock=clock, seed=21, own_supplies=["g2"]).start()
    try:
        cfg = bench.bench_config()
        assert cfg.slot("g2").power.psu.url == bench.own_psus["g2"].url and cfg.slot("g3").power.channel == 2
        t0 = clock.now()
        bench.drop_supply("g2", t0, t0 + 60.0)
        run_id, status, t_start = _plan_run(db, bench, clock, cfg, engine_config_for(clock), _power_plan())
        g2_on_at_end = bench.unit("g2").psu_model.output_on
        commands = [e.request.upper() for e in bench.own_psus["g2"].received.entries()]
    finally:
        bench.stop()
    try:
        assert status == "completed"
        report = run_report(db, run_id)
        assert report["suspensions"] == [] and report["status"] == "completed", report
        units = {u["slot"]: u for u in report["units"]}
        assert [units[s]["status"] for s in ("g1", "g2", "g3")] == ["completed"] * 3
        assert units["g1"]["gaps"] == units["g3"]["gaps"] == []
        (gap,) = units["g2"]["gaps"]
        # from the start to g2's first frame after the supply reading (every 10 s) that found it listening
        # again at +60 s (power sent again then)
        assert gap["t_from"] == pytest.approx(t_start, abs=2.0) and t_start + 60.0 <= gap["t_to"] <= t_start + 62.0
        assert gap["reason"] == "link"          # the kind of outage (a link of the unit's)
        kinds = [k for k, _ in _events(db, run_id)]
        assert kinds.count("unit_fault") == 1 and kinds.count("unit_recovered") == 1
        assert kinds.count("unit_power_restored") == 1 and "unit_power_failed" in kinds
        assert not any(k in ("run_failed", "step_failed") for k in kinds)
        assert not g2_on_at_end                  # the safe state reached it too
        # its settings and the commanded output sent again once it answered, then off in the safe state
        assert [c for c in commands if c.startswith("OUTP") and not c.endswith("?")][-2:] == ["OUTP ON", "OUTP OFF"]
    finally:
        db.dispose()


def test_own_supply_lost_for_good_fails_only_its_unit(tmp_path):
    """g2's own supply stops answering at +20 s and never comes back: g2's run ends failed with its gap
    to the end, the others complete, and the parent's reason says that g2's supply missed the safe
    state's power-off."""
    from bench.engine.steps import GyroPower, Plan, Record

    db = open_database(f"sqlite:///{tmp_path / 'psu-lost.sqlite'}")
    clock = lockstep_clock(None, 25)
    bench = MultiGyroBench(units=3, clock=clock, seed=25, own_supplies=["g2"]).start()
    try:
        cfg = bench.bench_config()
        bench.drop_supply("g2", clock.now() + 20.0)
        plan = Plan(name="power", steps=[GyroPower(on=True), Record(duration_s=60.0, labels={"p": 1})])
        run_id, status, t_start = _plan_run(db, bench, clock, cfg, engine_config_for(clock), plan)
        g2_still_on = bench.unit("g2").psu_model.output_on
    finally:
        bench.stop()
    try:
        assert status == "completed" and g2_still_on          # nobody could switch it off
        report = run_report(db, run_id)
        units = {u["slot"]: u for u in report["units"]}
        assert [units[s]["status"] for s in ("g1", "g2", "g3")] == ["completed", "failed", "completed"]
        (gap,) = units["g2"]["gaps"]
        assert t_start + 20.0 <= gap["t_from"] <= t_start + 31.0 and gap["frames_missing"] > 0
        assert "1 of 3 gyro units failed: g2: power supply link down" in report["status_reason"]
        assert "g2: its supply did not take the last command (output off)" in report["status_reason"]
    finally:
        db.dispose()


def test_own_supply_unreachable_suspends_the_run_under_suspend(tmp_path):
    db = open_database(f"sqlite:///{tmp_path / 'psu-suspend.sqlite'}")
    clock = lockstep_clock(None, 22)
    bench = MultiGyroBench(units=3, clock=clock, seed=22, own_supplies=["g2"]).start()
    try:
        cfg = bench.bench_config().model_copy(update={"unit_faults": "suspend"})
        ec = engine_config_for(clock).model_copy(update={"settle_s": 20.0})
        t0 = clock.now()
        bench.drop_supply("g2", t0, t0 + 60.0)
        run_id, status, t_start = _plan_run(db, bench, clock, cfg, ec, _power_plan())
    finally:
        bench.stop()
    try:
        assert status == "completed"
        report = run_report(db, run_id)
        (susp,) = report["suspensions"]
        assert susp["reason"].startswith("g2: power supply link down")
        assert susp["t_from"] == pytest.approx(t_start, abs=2.0)
        assert susp["t_to"] == pytest.approx(t_start + 60.0 + 20.0, abs=2.5)      # supply back, then settled
        units = {u["slot"]: u for u in report["units"]}
        assert [units[s]["status"] for s in ("g1", "g2", "g3")] == ["completed"] * 3
        kinds = [k for k, _ in _events(db, run_id)]
        assert "unit_fault" not in kinds and kinds.count("unit_power_restored") == 1
    finally:
        db.dispose()


def test_shared_supply_unreachable_is_one_bench_fault(tmp_path):
    """The bench's multi-channel supply (g1, g2 on channels 1, 2) refuses connections from the start to
    bench time +60 s, while g3 has a supply of its own: that is one condition of the bench (the run
    suspends once, "power supply link down"), not a fault of g1 and g2; g3 is untouched; g1 and g2 get
    their settings and power sent again once the supply answers, and every unit's run completes."""
    db = open_database(f"sqlite:///{tmp_path / 'psu-shared.sqlite'}")
    clock = lockstep_clock(None, 26)
    bench = MultiGyroBench(units=3, clock=clock, seed=26, own_supplies=["g3"]).start()
    try:
        cfg = bench.bench_config()      # unit_faults "continue": a unit's own faults would not suspend
        assert cfg.unit_faults == "continue" and cfg.slot("g2").power.channel == 2
        ec = engine_config_for(clock).model_copy(update={"settle_s": 20.0})
        t0 = clock.now()
        bench.drop_supply(None, t0, t0 + 60.0)
        run_id, status, t_start = _plan_run(db, bench, clock, cfg, ec, _power_plan())
        on_at_end = [bench.unit(s).psu_model.output_on for s in ("g1", "g2", "g3")]
        shared = [e.request.upper() for e in bench.psu.received.entries()]
        own = [e.request.upper() for e in bench.own_psus["g3"].received.entries()]
    finally:
        bench.stop()
    try:
        assert status == "completed"
        report = run_report(db, run_id)
        (susp,) = report["suspensions"]
        assert susp["reason"].startswith("power supply link down"), susp
        assert "g3" not in susp["reason"]
        assert susp["t_from"] == pytest.approx(t_start, abs=2.0)
        assert susp["t_to"] == pytest.approx(t_start + 60.0 + 20.0, abs=12.5)     # supply back (read every 10 s), settled
        units = {u["slot"]: u for u in report["units"]}
        assert [units[s]["status"] for s in ("g1", "g2", "g3")] == ["completed"] * 3
        assert units["g3"]["gaps"] == []
        kinds = [k for k, _ in _events(db, run_id)]
        assert "unit_fault" not in kinds and "unit_power_failed" not in kinds
        assert kinds.count("power_failed") == 1 and kinds.count("unit_power_restored") == 2
        assert not any(k in ("run_failed", "step_failed") for k in kinds)
        assert on_at_end == [False, False, False]           # the safe state reached every channel
        # power sent again on both channels once the supply answered, then off in the safe state
        for ch in (1, 2):
            outp = [c for c in shared if c.startswith(f"INST:NSEL {ch};:OUTP") and not c.endswith("?")]
            assert outp[-2:] == [f"INST:NSEL {ch};:OUTP ON", f"INST:NSEL {ch};:OUTP OFF"], shared
        assert [c for c in own if c.startswith("OUTP") and not c.endswith("?")] == ["OUTP ON", "OUTP OFF"]
    finally:
        db.dispose()


def test_drop_supply_needs_an_own_supply():
    bench = MultiGyroBench(units=2, clock=lockstep_clock(None, 23), own_supplies=["g2"])
    with pytest.raises(ValueError, match="channel 1 of the bench's supply"):
        bench.drop_supply("g1", 10.0)
    with pytest.raises(ValueError, match="the bench's supply.*not after"):
        bench.drop_supply(None, 10.0, 5.0)
    with pytest.raises(ValueError, match="at least one slot stays"):
        MultiGyroBench(units=2, clock=lockstep_clock(None, 23), own_supplies=["g1", "g2"])
    with pytest.raises(ValueError, match="own_supplies: no slot g5"):
        MultiGyroBench(units=2, clock=lockstep_clock(None, 23), own_supplies=["g5"])


# ---- a line's reconnect gap in bench time --------------------------------------------------------------
@pytest.mark.parametrize("paces", [(None, 300.0)])
def test_reconnect_gap_is_bench_time_whatever_the_pace(tmp_path, paces):
    """g2's line drops at +40 s and listens again at +70 s (bench time): the gap its link records is
    the same at two paces (the receiver retries by bench time), and ends on the first reconnect
    attempt after +70 s."""
    from bench.engine.steps import GyroPower, Plan, Record

    plan = Plan(name="line", steps=[GyroPower(on=True), Record(duration_s=120.0, labels={"p": 1})])
    seen = []
    for k, pace in enumerate(paces):
        db = open_database(f"sqlite:///{tmp_path / f'pace{k}.sqlite'}")
        clock = lockstep_clock(pace, 24)
        bench = MultiGyroBench(units=3, clock=clock, seed=24).start()
        try:
            cfg = bench.bench_config()
            t0 = clock.now()
            bench.drop_line("g2", t0 + 40.0, t0 + 70.0)
            run_id, status, t_start = _plan_run(db, bench, clock, cfg, engine_config_for(clock), plan)
        finally:
            bench.stop()
        try:
            assert status == "completed"
            report = run_report(db, run_id)
            units = {u["slot"]: u for u in report["units"]}
            (gap,) = units["g2"]["gaps"]
            assert gap["reason"] == "link" and units["g1"]["gaps"] == units["g3"]["gaps"] == []
            # every frame the simulator could not deliver is in the gap, none lost beside it
            undelivered = sum(not f.delivered for f in bench.unit("g2").gyro.sent_frames())
            assert gap["frames_missing"] == undelivered > 0
            assert units["g2"]["frames"] + undelivered == units["g1"]["frames"]
            seen.append((gap["t_from"] - t_start, gap["t_to"] - t_start, gap["frames_missing"]))
        finally:
            db.dispose()
    assert seen[0] == seen[1]
    t_from, t_to, _ = seen[0]
    # from g2's last frame before the drop at +40 s to its first after the reconnect at or after +70 s
    assert 38.0 <= t_from < 40.0 and 70.0 <= t_to <= 72.0


@pytest.mark.parametrize("back_before_resume", [False, True])
def test_resume_rebuilds_what_the_shared_supply_missed(tmp_path, back_before_resume):
    """The bench's multi-channel supply (g1, g2) refuses connections from the start, so the power-on
    misses both channels (each unit due its commanded state, its frames the bench's condition); the
    engine dies (kill -9) at +100 s while the run is suspended.  Those per-unit states are not in the
    checkpoint: the resume sends every unit's settings and the commanded output again, and whatever
    misses them is due again.  Supply still down at the resume (back at +300 s): the run suspends on it
    again and the power goes out once it answers; supply back before the resume: the resume's own
    commands power both channels and nothing is due after them.  Either way no unit is faulted and all complete."""
    from tests.test_engine_doubles import Killed, Scripted, kill_at

    db = open_database(f"sqlite:///{tmp_path / 'psu-resume.sqlite'}")
    clock = lockstep_clock(None, 27)
    clock.fixed_outage_s = 60.0                  # the outage lasts 60 bench seconds after the checkpoint
    bench = MultiGyroBench(units=3, clock=clock, seed=27, own_supplies=["g3"]).start()
    try:
        cfg = bench.bench_config()
        ec = engine_config_for(clock).model_copy(update={"settle_s": 20.0, "checkpoint_period_s": 30.0})
        t0 = clock.now()
        bench.drop_supply(None, t0, t0 + (130.0 if back_before_resume else 300.0))
        run_id = new_run(db, procedure="power", parameters={}, config_snapshot=cfg.model_dump(mode="json"),
                         gyro_id=None, bench_name=cfg.name, units=cfg.assign_gyros(["P-1", "P-2", "P-3"]))
        for attempt in ("run", "resume"):
            store = SqlRunStore(db, geometry=cfg.turntable.geometry)
            devices = build_devices(cfg, clock)
            control = Scripted(clock, [(100.0, kill_at(100.0))]) if attempt == "run" else None
            engine = Engine(devices, store, clock, cfg, control=control, engine_config=ec)
            try:
                if attempt == "run":
                    with pytest.raises(Killed):
                        engine.run(str(run_id), _power_plan())
                else:
                    status = engine.resume(str(run_id))
            finally:
                store.close(run_id)
                close_devices(devices)
            if attempt == "run":
                n_before = len(bench.psu.received.entries())
        shared = [e.request.upper() for e in bench.psu.received.entries()]
    finally:
        bench.stop()
    try:
        assert status == "completed"
        with db.session() as s:
            (t_resume,) = [e.t_bench for e in queries.list_events(s, run_id) if e.kind == "run_resumed"]
        assert t0 + 130.0 < t_resume < t0 + 300.0      # between the two supply outcomes
        report = run_report(db, run_id)
        units = {u["slot"]: u for u in report["units"]}
        assert [units[s]["status"] for s in ("g1", "g2", "g3")] == ["completed"] * 3
        events = _events(db, run_id)
        kinds = [k for k, _ in events]
        assert "unit_fault" not in kinds and "unit_power_failed" not in kinds
        resumed_at = kinds.index("run_resumed")
        after = kinds[resumed_at:]
        assert all(s["reason"].startswith("power supply link down") for s in report["suspensions"])
        for ch in (1, 2):
            outp = [c for c in shared[n_before:] if c.startswith(f"INST:NSEL {ch};:OUTP") and not c.endswith("?")]
            assert outp[-2:] == [f"INST:NSEL {ch};:OUTP ON", f"INST:NSEL {ch};:OUTP OFF"], shared[n_before:]
            assert set(outp[:-1]) == {f"INST:NSEL {ch};:OUTP ON"}
        if back_before_resume:      # the resume's own commands reached the supply: nothing was due after them
            assert "power_failed" not in after and "unit_power_restored" not in after
        else:                       # missed again at the resume: due again, sent once the supply answered
            assert after.count("power_failed") == 1 and after.count("unit_power_restored") == 2
            last_susp = report["suspensions"][-1]
            assert last_susp["t_to"] >= t0 + 300.0
    finally:
        db.dispose()
