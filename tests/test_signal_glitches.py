"""Isolated glitches (bench.signal.isolated_glitches, bench.fit.prep.screen_glitches): corrupted gyro
frames and a probe's power-on 85.0 C are found; noise, steps, ramps, sharp reversals, warm-ups and
quantised soaks are not."""
from __future__ import annotations

import numpy as np

from bench.fit.base import Dataset
from bench.fit.channels import fit_channels
from bench.fit.prep import screen_glitches
from bench.signal import isolated_glitches

DS18B20_LSB = 0.0625


def _gyro(n: int, seed: int, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A day's worth of gyro bias: white noise 0.5 deg/h plus a warm-up, a mode hop, a slow wave."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    x = (0.5 * rng.standard_normal(n) + 3.0 * np.exp(-t / 900.0) + 0.8 * (t > 0.6 * t[-1])
         + 0.4 * np.sin(2 * np.pi * t / 7200.0))
    return t, x


def _probe(dt: float, rate_c_per_min: float, hours: float) -> tuple[np.ndarray, np.ndarray]:
    """A chamber probe on a triangle program (sharp reversals) read as a DS18B20 (0.0625-C steps)."""
    t = np.arange(0.0, hours * 3600.0, dt)
    period = 2 * 40.0 / rate_c_per_min * 60.0           # -15 .. 25 C and back
    phase = (t % period) / period
    temp = -15.0 + 40.0 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    noisy = temp + 0.02 * np.random.default_rng(3).standard_normal(len(t))
    return t, np.round(noisy / DS18B20_LSB) * DS18B20_LSB


def test_noise_steps_warmup_and_waves_are_not_glitches():
    for seed in range(3):
        t, x = _gyro(86400, seed)
        assert not isolated_glitches(t, x).any()
    # a three-sigma rule would flag hundreds of these samples
    t, x = _gyro(86400, 0)
    assert np.sum(np.abs(x - np.median(x)) > 3 * 0.5) > 100


def test_corrupted_frames_are_found_and_nothing_else():
    t, x = _gyro(86400, 1)
    rng = np.random.default_rng(11)
    single = rng.choice(np.arange(100, 86300), 12, replace=False)
    x[single] += rng.choice([-1.0, 1.0], 12) * 25.0        # 50 sigma of the noise
    x[40000:40003] = 400.0                                 # three consecutive garbled frames
    found = np.flatnonzero(isolated_glitches(t, x))
    assert set(found) == set(single) | {40000, 40001, 40002}


def test_quantised_probe_on_fast_ramps_with_sharp_reversals_is_clean_and_85_c_is_found():
    for dt, rate in ((1.0, 2.0), (10.0, 5.0), (5.0, 1.0)):
        t, temp = _probe(dt, rate, 12.0)
        assert not isolated_glitches(t, temp).any(), (dt, rate)
        bad = temp.copy()
        where = [len(t) // 3, len(t) // 2, len(t) // 2 + 1]
        bad[where] = 85.0
        assert list(np.flatnonzero(isolated_glitches(t, bad))) == where, (dt, rate)


def test_a_flat_soak_of_one_reading_has_no_glitch_but_a_power_on_reading_is_one():
    t = np.arange(3600.0)
    soak = np.full(len(t), 25.0)
    soak[::97] += DS18B20_LSB                               # the last bit toggling now and then
    assert not isolated_glitches(t, soak).any()
    soak[1800] = 85.0
    assert list(np.flatnonzero(isolated_glitches(t, soak))) == [1800]


def test_gaps_and_missing_readings_split_the_record():
    t, x = _gyro(20000, 2)
    x[5000:5010] = np.nan
    t = np.where(np.arange(len(t)) >= 12000, t + 3600.0, t)   # a logger outage of an hour
    assert not isolated_glitches(t, x).any()
    x[12000] = 60.0                                          # first reading after the outage
    assert list(np.flatnonzero(isolated_glitches(t, x))) == [12000]


def _bench_run(seed: int, glitches: bool) -> Dataset:
    t, temp = _probe(1.0, 1.0, 8.0)
    rng = np.random.default_rng(seed)
    true_t = temp + 0.0
    gyro = 2.0 + 0.15 * true_t + 0.002 * true_t ** 2 + 0.3 * rng.standard_normal(len(t))
    if glitches:
        gyro = gyro.copy()
        gyro[[1000, 9000, 20000]] = [900.0, -700.0, 1200.0]
        temp = temp.copy()
        temp[[5000, 15000]] = 85.0
    return Dataset({"time_s": t, "gyro_x": gyro, "temp_t1": temp}, {})


def test_screen_names_what_it_removed_and_the_fit_sees_clean_data():
    ds = _bench_run(5, glitches=True)
    screened, found = screen_glitches(ds)
    assert found == {"gyro_x": {"samples": 3, "time_s": [1000.0, 9000.0, 20000.0]},
                     "temp_t1": {"samples": 2, "time_s": [5000.0, 15000.0]}}
    assert np.isnan(screened["gyro_x"][[1000, 9000, 20000]]).all()
    assert np.isnan(screened["temp_t1"][[5000, 15000]]).all()
    assert screen_glitches(_bench_run(5, glitches=False))[1] == {}

    clean, _ = fit_channels("t1 + t1^2", _bench_run(5, False), _bench_run(6, False), ["x"], {})
    dirty, _ = fit_channels("t1 + t1^2", ds, _bench_run(6, glitches=True), ["x"], {})
    assert dirty["glitches_removed"]["validation"]["temp_t1"]["samples"] == 2
    for name, value in clean["channels"]["x"]["coefficients"].items():
        assert abs(dirty["channels"]["x"]["coefficients"][name] - value) <= 1e-3 * max(1.0, abs(value)), name
    c, d = clean["channels"]["x"]["validation"], dirty["channels"]["x"]["validation"]
    assert d["std100_dph"] <= 1.02 * c["std100_dph"]
    assert abs(d["validation_coverage"] - c["validation_coverage"]) < 1e-3


def test_close_loop_on_glitched_runs_scores_as_on_clean_ones():
    """A corpus case with corrupted gyro frames and 85.0-C probe readings in both runs: the report names
    them, and the referee, judging against the clean case, passes the channel as it does unglitched."""
    from bench.fit.closeloop import close_loop
    from tests.corpus.cases import make_case
    from tests.corpus.referee import score_channel

    case = make_case("effect_validation_colder", 1)
    rng = np.random.default_rng(4)

    def glitched(ds: Dataset) -> tuple[Dataset, dict[str, list[float]]]:
        cols, where = {}, {}
        for name in ("gyro_y", "temp_t1", "temp_t2"):
            x = np.array(ds[name], dtype=float)
            idx = np.sort(rng.choice(np.arange(50, len(x) - 50), 3, replace=False))
            x[idx] = 85.0 if name.startswith("temp_") else x[idx] + 500.0
            cols[name], where[name] = x, [float(t) for t in ds.time[idx]]
        return ds.with_columns(**cols), where

    train, where_train = glitched(case.train)
    validate, where_validate = glitched(case.validate)
    (ch,) = case.truth
    report = close_loop(train, validate, case.truth[ch].formula, channels=[ch])
    assert {c: v["time_s"] for c, v in report["glitches_removed"]["training"].items()} == where_train
    assert {c: v["time_s"] for c, v in report["glitches_removed"]["validation"].items()} == where_validate
    score = score_channel(case, ch, report["channels"][ch])
    assert score.passed, score.reasons
    from bench.fit.closeloop_report import render_close_loop_report
    page = render_close_loop_report(report, train, validate)
    assert "isolated glitches set missing" in page and "temp_t2" in page


def test_probe_readings_averaged_by_a_logger_are_not_glitches():
    """The seventh referee's 10-s averages of DS18B20 readings (deviations mostly exactly zero, now and
    then 0.03 C) and, on a cleaner probe, a lone 0.5-C reading: no probe on a thermal mass leaves its
    course by a degree for one reading, so below that a temperature is not a glitch; in a gyro column
    the same excursion is one."""
    import os
    import tempfile

    from bench.commands.common import load_dataset
    from tests.referee7.cases import build_case
    from tests.referee7.score import write_csv

    run = build_case("complete_avg10", 2)["runs"]["validate"]
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "validate.csv")
        write_csv(path, run["meta"], run["cols"])
        ds = load_dataset(path, None)
    assert screen_glitches(ds)[1] == {}

    t = np.arange(7200.0)
    clean = 20.0 + 1e-4 * t + 0.002 * np.random.default_rng(8).standard_normal(len(t))
    clean[3000] += 0.5
    found = screen_glitches(Dataset({"time_s": t, "temp_t1": clean, "gyro_x": clean}, {}))[1]
    assert found == {"gyro_x": {"samples": 1, "time_s": [3000.0]}}


def test_each_stretch_of_steady_conditions_is_judged_on_its_own():
    """The ninth referee's multi-position training run ends with one sample in the next position (the
    Earth rate's projection jumps by 10-40 deg/h): a position held for one sample is not a glitch."""
    t, x = _gyro(3600, 4)
    orientation = np.where(t < 3599.0, "WDS", "USE")
    x[-1] += 40.0
    ds = Dataset({"time_s": t, "gyro_x": x, "orientation": orientation}, {})
    assert screen_glitches(ds)[1] == {}
    assert isolated_glitches(t, x)[-1]          # judged as one record, it would be
    # the same for a turntable rate commanded for the last sample, and for the power switched on there
    assert screen_glitches(Dataset({"time_s": t, "gyro_x": x, "table_rate_dps": np.where(t < 3599.0, 0.0, 0.01)},
                                   {}))[1] == {}
    assert screen_glitches(Dataset({"time_s": t, "gyro_x": x, "power": np.where(t < 3599.0, 0.0, 1.0)}, {}))[1] == {}
    assert screen_glitches(Dataset({"time_s": t, "gyro_x": x, "power": np.ones(len(t))}, {}))[1] != {}


def test_the_fit_command_says_what_it_set_missing(tmp_path):
    from typer.testing import CliRunner

    from bench.cli import app
    from bench.fit.csvio import write_csv

    train, validate = tmp_path / "train.csv", tmp_path / "validate.csv"
    write_csv(_bench_run(5, glitches=True), train)
    write_csv(_bench_run(6, glitches=False), validate)
    out = tmp_path / "fit.json"
    res = CliRunner().invoke(app, ["fit", "t1 + t1^2", str(train), str(validate), "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert "glitches set missing" in res.output and "training gyro_x 3 (first at t = 1000 s)" in res.output
    import json
    doc = json.loads(out.read_text())
    assert doc["glitches_removed"] == {"training": {"gyro_x": {"samples": 3, "time_s": [1000.0, 9000.0, 20000.0]},
                                                    "temp_t1": {"samples": 2, "time_s": [5000.0, 15000.0]}},
                                       "validation": {}}


def test_an_hrg_resonance_frequency_glitch_is_found_and_a_staircase_is_not_one():
    """An HRG's resonance frequency (a few kHz, moving by 0.12 Hz/C) with one garbled reading; and the
    same quantity computed from a DS18B20's readings (0.0075-Hz steps, 37x its noise, the last bit
    toggling on every ramp): a signal that steps between levels all the time has no glitch there."""
    t, probe = _probe(1.0, 1.0, 4.0)
    rng = np.random.default_rng(9)
    true_temp = np.interp(t, t[::60], probe[::60])                 # the probe's course without its steps
    freq = 5000.0 - 0.12 * true_temp + 2e-4 * rng.standard_normal(len(t))
    freq[7000] = 5100.0
    found = screen_glitches(Dataset({"time_s": t, "freq_x": freq, "temp_t1": probe}, {}))[1]
    assert found == {"freq_x": {"samples": 1, "time_s": [7000.0]}}
    stairs = 5000.0 - 0.12 * probe + 2e-4 * rng.standard_normal(len(t))
    assert not isolated_glitches(t, stairs).any()
    stairs[7000] = 5100.0
    assert list(np.flatnonzero(isolated_glitches(t, stairs))) == [7000]
