"""Close the loop on data from the bench simulator's own physics (bench.sim.offline), with a scenario
effect the declared model lacks."""
from __future__ import annotations

from bench.fit.closeloop import close_loop, public
from bench.sim.offline import simulate
from bench.sim.scenario import Scenario

DECLARED_X = "t1 + t1^2 + t1^3 + (t1-t3) + dt1"      # the default scenario's own bias form for x


def _startup_profile(points):
    prof = []
    for temp in points:
        prof += [("power", "off"), ("hold", temp, 4 * 3600), ("power", "on"), ("hold", temp, 2 * 3600)]
    return prof


def test_warmup_missing_from_the_declared_model_is_found_on_simulator_data():
    scenario = Scenario.builtin("default").with_changes(
        effects={"warmup": {"tau_s": 1200.0, "amplitude_dph": {"x": 0.3, "y": 0.0, "z": 0.0}}})
    train = simulate(scenario, _startup_profile([-30, 0, 30, 55]), 2.0, seed=11)
    validate = simulate(scenario, _startup_profile([45, -15, 15]), 2.0, seed=12)
    ch = public(close_loop(train, validate, DECLARED_X, channels=["x"]))["channels"]["x"]
    assert [e["kind"] for e in ch["effects_added"]][:1] == ["warmup"], ch["findings"]
    tau = ch["effects_added"][0]["params"]["tau_s"]
    assert 800 < tau < 1800, tau
    assert ch["after"]["validation_std100_dph"] < 0.5 * ch["before"]["validation_std100_dph"]


def test_complete_declared_model_on_simulator_data_adds_nothing():
    prof = [("hold", 20.0, 3600), ("ramp", 55.0, 1.0), ("hold", 55.0, 3 * 3600), ("ramp", -25.0, 0.5),
            ("hold", -25.0, 3 * 3600), ("ramp", 30.0, 2.0), ("hold", 30.0, 2 * 3600)]
    prof_v = [("hold", 10.0, 3600), ("ramp", -20.0, 0.8), ("hold", -20.0, 2 * 3600), ("ramp", 50.0, 1.5),
              ("hold", 50.0, 3 * 3600), ("ramp", 15.0, 0.3)]
    train = simulate("default", prof, 2.0, seed=3)
    validate = simulate("default", prof_v, 2.0, seed=4)
    ch = public(close_loop(train, validate, DECLARED_X, channels=["x"]))["channels"]["x"]
    assert ch["effects_added"] == [], ch["findings"]
    assert ch["verdict"] == "no_effect_missing", ch["findings"]
