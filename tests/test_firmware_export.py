"""Coefficient export for firmware: PX4 and ArduPilot parameter files and a C header.

Each export is applied the way its firmware does, re-implemented here from the formats' public
definitions (PX4 ``TemperatureCompensation::calc_thermal_offsets_*`` and ``apply_corrections_gyro``;
ArduPilot ``AP_InertialSensor_TCal::correct_sensor`` / ``polynomial_eval`` followed by the gyro offset
subtraction in ``_rotate_and_correct_gyro``), and must reproduce the product's own compensation
(``models.compensate``) within 1e-6 deg/h over and beyond the validity range.
"""
from __future__ import annotations

import math
import shutil
import subprocess

import numpy as np
import pytest

from bench.fit import models
from bench.fit.base import Dataset
from bench.fit.formula import compiled_from_recipe
from bench.fit.firmware import NotExpressible, ardupilot_params, c_header, px4_params, render
from tests.test_fit_core_synth import CAL_PROFILE, VAL_PROFILE, thermal_run

RAD_S_IN_DPH = math.pi / 180.0 / 3600.0      # rad/s per deg/h, written out independently of the product
TOL_DPH = 1e-6
# per-axis static truth (deg/h about 25 C): a MEMS-size y axis (hundreds of deg/h) checks the unit scale
AXIS_TRUTH = {"y": (350.0, -12.5, 0.08, -0.0021), "z": (-40.0, 3.0, -0.015, 0.0004)}


def _three_axis(profile, seed):
    ds, truth = thermal_run(profile, truth="dynamic", seed=seed)
    rng = np.random.default_rng(seed + 100)
    d = truth["true_t"]["t1"] - 25.0
    extra = {}
    for ax, (a0, a1, a2, a3) in AXIS_TRUTH.items():
        extra[f"gyro_{ax}"] = a0 + a1 * d + a2 * d ** 2 + a3 * d ** 3 + rng.normal(0.0, 0.05, len(d))
    return ds.with_columns(**extra)


@pytest.fixture(scope="module")
def cal():
    return _three_axis(CAL_PROFILE, 61)


@pytest.fixture(scope="module")
def static3(cal):
    return [models.fit_model("static", cal, ch, probe="t1") for ch in ("x", "y", "z")]


@pytest.fixture(scope="module")
def sweep(static3):
    """Temperatures across the validity range and 15 C beyond both ends; raw readings in deg/h."""
    lo, hi = static3[0].validity["signals"]["temp:temp_t1"]
    t = np.concatenate([np.linspace(lo - 15.0, hi + 15.0, 4001), [lo, hi]])
    rng = np.random.default_rng(5)
    cols = {"time_s": np.arange(len(t), dtype=float), "temp_t1": t}
    for ch in ("x", "y", "z"):
        cols[f"gyro_{ch}"] = rng.normal(0.0, 500.0, len(t))
    return Dataset(cols)


# ------------------------------------------------------------------------------------- PX4
def parse_px4(text: str) -> dict[str, float]:
    """QGroundControl parameter file: 'vehicle component name value type', tab separated."""
    params = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split("\t")
        assert len(fields) == 5, line
        vehicle, component, name, value, ptype = fields
        assert (vehicle, component) == ("1", "1")
        if name.endswith("_ID") or name == "TC_G_ENABLE":
            assert ptype == "6" and value.lstrip("-").isdigit(), line    # int32
        else:
            assert ptype == "9", line                                    # float
        params[name] = float(value)
    return params


def px4_corrected_rads(p: dict[str, float], i: int, axis: int, raw_rads: np.ndarray, temp: np.ndarray) -> np.ndarray:
    """calc_thermal_offsets_3D + apply_corrections_gyro (scale 1)."""
    g = f"TC_G{i}"
    tmin, tmax, tref = p[f"{g}_TMIN"], p[f"{g}_TMAX"], p[f"{g}_TREF"]
    delta = np.where(temp > tmax, tmax - tref, np.where(temp < tmin, tmin - tref, temp - tref))
    x = [p[f"{g}_X{k}_{axis}"] for k in range(4)]
    offset = x[0] + x[1] * delta + x[2] * delta ** 2 + x[3] * delta ** 3
    return raw_rads - offset


def test_px4_file_lines_units_and_convention(static3, sweep):
    text = px4_params("KVH-7", static3, instance=1, device_id=2293768, label="static v1")
    p = parse_px4(text)
    g = "TC_G1"
    want = {"TC_G_ENABLE", f"{g}_ID", f"{g}_TREF", f"{g}_TMIN", f"{g}_TMAX"} | \
           {f"{g}_X{k}_{a}" for k in range(4) for a in range(3)}
    assert set(p) == want
    assert p[f"{g}_ID"] == 2293768 and p["TC_G_ENABLE"] == 1
    assert p[f"{g}_TREF"] == 25.0                                 # the product's reference, kept
    lo, hi = static3[0].validity["signals"]["temp:temp_t1"]
    assert (p[f"{g}_TMIN"], p[f"{g}_TMAX"]) == (lo, hi)
    # units: X_k = A_k converted from deg/h/C^k to rad/s/C^k
    for a, res in enumerate(static3):
        for k in range(4):
            assert p[f"{g}_X{k}_{a}"] == pytest.approx(res.coefficients[f"A{k}"] * RAD_S_IN_DPH, rel=1e-12, abs=1e-300)
    assert abs(p[f"{g}_X0_1"]) == pytest.approx(350.0 * RAD_S_IN_DPH, rel=0.01)   # ~1.7e-3 rad/s
    # the firmware's evaluation reproduces the product's compensation, clipping included
    t = sweep["temp_t1"]
    for a, res in enumerate(static3):
        want_dph, flagged = models.compensate(res, sweep)
        got_dph = px4_corrected_rads(p, 1, a, sweep[f"gyro_{'xyz'[a]}"] * RAD_S_IN_DPH, t) / RAD_S_IN_DPH
        err = np.max(np.abs(got_dph - want_dph))
        assert err < TOL_DPH, f"axis {a}: {err} deg/h"
        assert flagged.any() and not flagged.all()
        # PX4 holds parameters as float32: that rounding alone stays far below the gyro's noise
        p32 = {k: float(np.float32(v)) for k, v in p.items()}
        got32 = px4_corrected_rads(p32, 1, a, sweep[f"gyro_{'xyz'[a]}"] * RAD_S_IN_DPH, t) / RAD_S_IN_DPH
        assert np.max(np.abs(got32 - want_dph)) < 1e-4


# -------------------------------------------------------------------------------- ArduPilot
def parse_ardupilot(text: str) -> dict[str, float]:
    params = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, value = line.split()
        params[name] = float(value)
    return params


def ardupilot_corrected_rads(p: dict[str, float], imu: int, axis: str, raw: np.ndarray, temp: np.ndarray) -> np.ndarray:
    """AP_InertialSensor_TCal::correct_sensor (TEMP_REFERENCE 35, coefficients x 1e-6, no constant
    term), then ``gyro -= gyro_offset`` (AP_InertialSensor_Backend::_rotate_and_correct_gyro)."""
    t = f"INS_TCAL{imu}"
    assert p[f"{t}_ENABLE"] == 1
    tmin, tmax = p[f"{t}_TMIN"], p[f"{t}_TMAX"]
    c = [p[f"{t}_GYR{k}_{axis}"] for k in (1, 2, 3)]

    def poly(tdiff):
        return (c[0] + (c[1] + c[2] * tdiff) * tdiff) * tdiff * 1.0e-6

    temperature = np.clip(temp, tmin, tmax)
    cal_temp = min(max(p[f"INS_GYR{imu}_CALTEMP"], tmin), tmax)
    v = raw - poly(temperature - 35.0)
    v = v + poly(cal_temp - 35.0)
    offs = "INS_GYROFFS" if imu == 1 else f"INS_GYR{imu}OFFS"
    return v - p[f"{offs}_{axis}"]


@pytest.mark.parametrize("imu,caltemp", [(1, None), (2, 20.0)])
def test_ardupilot_params_reproduce_the_product(static3, sweep, imu, caltemp):
    text = ardupilot_params("KVH-7", static3, imu=imu, caltemp_c=caltemp)
    p = parse_ardupilot(text)
    t = f"INS_TCAL{imu}"
    offs = "INS_GYROFFS" if imu == 1 else f"INS_GYR{imu}OFFS"
    want = {f"{t}_ENABLE", f"{t}_TMIN", f"{t}_TMAX", f"INS_GYR{imu}_CALTEMP"} | \
           {f"{t}_GYR{k}_{a}" for k in (1, 2, 3) for a in "XYZ"} | {f"{offs}_{a}" for a in "XYZ"}
    assert set(p) == want
    assert p[f"INS_GYR{imu}_CALTEMP"] == (35.0 if caltemp is None else caltemp)
    # units and the fixed 35 C reference: GYR1 = d bias/dT at 35 C in rad/s/C, times 1e6
    a = static3[1].coefficients
    slope_35 = a["A1"] + 2 * a["A2"] * 10.0 + 3 * a["A3"] * 100.0
    assert p[f"{t}_GYR1_Y"] == pytest.approx(slope_35 * RAD_S_IN_DPH * 1e6, rel=1e-9)
    assert p[f"{t}_GYR3_Y"] == pytest.approx(a["A3"] * RAD_S_IN_DPH * 1e6, rel=1e-9)
    for ch, res in zip("XYZ", static3):
        want_dph, _ = models.compensate(res, sweep)
        got = ardupilot_corrected_rads(p, imu, ch, sweep[f"gyro_{ch.lower()}"] * RAD_S_IN_DPH, sweep["temp_t1"])
        err = np.max(np.abs(got / RAD_S_IN_DPH - want_dph))
        assert err < TOL_DPH, f"axis {ch}: {err} deg/h"


# ------------------------------------------------------------------------------- refusals
def test_models_a_parameter_format_cannot_express_are_refused(cal):
    dyn = models.fit_model("dynamic", cal, "x", probe="t1", grad=("t1", "t2"))
    for fn in (px4_params, ardupilot_params):
        with pytest.raises(NotExpressible, match=r"dT/dt|temperatures"):
            fn("G", [dyn])
    grad_only = models.fit_model("t1 + (t1-t3)", cal, "x")
    with pytest.raises(NotExpressible, match=r"2 temperatures \(temp_t1, temp_t3"):
        px4_params("G", [grad_only])
    quartic = models.fit_model("(t1-25) + (t1-25)^2 + (t1-25)^4", cal, "x")
    with pytest.raises(NotExpressible, match="degree 4"):
        ardupilot_params("G", [quartic])
    with pytest.raises(NotExpressible, match="unknown format"):
        render("simulink", "G", [dyn])


# -------------------------------------------------------------------------------- C header
C_MAIN = r"""
#include <stdio.h>
#include "model.h"
int main(void) {
    double in[%(N)s_N_INPUTS];
    int ch, flagged, i;
    while (scanf("%%d", &ch) == 1) {
        for (i = 0; i < %(N)s_N_INPUTS; i++) {
            if (scanf("%%lf", &in[i]) != 1) return 2;
        }
        double b = %(n)s_bias_dph(ch, in, &flagged);
        printf("%%.17g %%d\n", b, flagged);
    }
    return 0;
}
"""


def _input_order(header: str) -> list[str]:
    keys = []
    for line in header.splitlines():
        if line.startswith(" *   in["):
            keys.append(line.split("] ", 1)[1].split(" ", 1)[0])
    return keys


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler (cc)")
def test_c_header_compiles_cleanly_and_reproduces_the_product(cal, static3, tmp_path):
    val = _three_axis(VAL_PROFILE, 62)
    # push part of the run outside the fitted ranges: clip + flag + hull
    val.columns["temp_t1"] = val["temp_t1"] + np.where(val.time > 20000, 15.0, 0.0)
    fits = {"static": static3,
            "dynamic": [models.fit_model("dynamic", cal, ch, probe="t1", grad=("t1", "t2")) for ch in ("x", "y")],
            "formula": [models.fit_model("t1 + (t1-t3)^2 + t1*dt1 + dt1^2", cal, "x")]}
    checked = 0
    for name, results in fits.items():
        header = c_header("KVH 7", results, label=f"{name} test")
        d = tmp_path / name
        d.mkdir()
        (d / "model.h").write_text(header)
        prefix = f"gb_kvh_7_{name}"
        (d / "main.c").write_text(C_MAIN % {"N": prefix.upper(), "n": prefix})
        cc = subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-o", str(d / "m"),
                             str(d / "main.c")], capture_output=True, text=True)
        assert cc.returncode == 0, cc.stderr
        assert cc.stderr == ""
        keys = _input_order(header)
        rows = []
        for ci, res in enumerate(results):
            s = compiled_from_recipe(res.definition["terms"], "", res.definition["rate_filter"]["window_s"]).signals(val)
            for j in range(0, len(val), 7):
                rows.append((ci, j, " ".join(repr(float(s[k][j])) if k in s else "0" for k in keys)))
        stdin = "\n".join(f"{ci} {vals}" for ci, _, vals in rows) + "\n"
        out = subprocess.run([str(d / "m")], input=stdin, capture_output=True, text=True, check=True).stdout.split("\n")
        got = np.array([float(line.split()[0]) for line in out if line])
        got_flag = np.array([line.split()[1] == "1" for line in out if line])
        preds = [models.predict(r, val) for r in results]
        want = np.array([preds[ci][0][j] for ci, j, _ in rows])
        want_flag = np.array([preds[ci][1][j] for ci, j, _ in rows])
        finite = np.isfinite(want)
        assert finite.sum() > 1000
        np.testing.assert_array_equal(np.isfinite(got), finite)
        err = np.max(np.abs(got[finite] - want[finite]))
        assert err < TOL_DPH, f"{name}: {err} deg/h"
        np.testing.assert_array_equal(got_flag, want_flag)
        assert want_flag.any() and not want_flag.all()
        checked += len(rows)
    assert checked > 5000


# ------------------------------------------------------------------------- CLI and HTTP API
@pytest.fixture()
def stored(tmp_path, static3, cal):
    from bench.storage import open_database, queries

    url = f"sqlite:///{tmp_path / 'fw.sqlite'}"
    db = open_database(url)
    dyn = [models.fit_model("dynamic", cal, ch, probe="t1", grad=("t1", "t2")) for ch in ("x", "y", "z")]
    with db.session() as s:
        queries.save_fits(s, "KVH-7", [], static3, accepted=True)
        queries.save_fits(s, "KVH-7", [], dyn, accepted=True)
        s.commit()
    yield db, url
    db.dispose()


def test_api_exports_and_refuses_with_the_reason(stored, static3):
    from fastapi.testclient import TestClient

    from api.app import create_app
    from tests.api_support import TOKENS, VIEWER

    db, _ = stored
    with TestClient(create_app(db, tokens=TOKENS)) as c:
        r = c.get("/gyros/KVH-7/coefficients/export?model=static&format=px4&px4_device_id=2293768", headers=VIEWER)
        assert r.status_code == 200, r.text
        assert r.headers["content-type"].startswith("text/plain")
        p = parse_px4(r.text)
        assert p["TC_G0_ID"] == 2293768
        assert p["TC_G0_X1_2"] == pytest.approx(static3[2].coefficients["A1"] * RAD_S_IN_DPH, rel=1e-12)
        r = c.get("/gyros/KVH-7/coefficients/export?model=static&format=ardupilot&ardupilot_imu=3", headers=VIEWER)
        assert r.status_code == 200 and "INS_TCAL3_GYR3_Z " in r.text and "INS_GYR3OFFS_X " in r.text
        r = c.get("/gyros/KVH-7/coefficients/export?model=dynamic&format=c-header", headers=VIEWER)
        assert r.status_code == 200 and "gb_kvh_7_dynamic_bias_dph" in r.text
        doc = c.get("/gyros/KVH-7/coefficients/export?model=static&format=json", headers=VIEWER).json()
        assert doc["schema"] == "gyrobench.fit.export" and [m["channel"] for m in doc["models"]] == ["x", "y", "z"]
        r = c.get("/gyros/KVH-7/coefficients/export?model=dynamic&format=px4", headers=VIEWER)
        assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
        assert "dT/dt" in r.json()["detail"]
        assert c.get("/gyros/KVH-7/coefficients/export?model=nope&format=px4", headers=VIEWER).status_code == 404
        assert c.get("/gyros/KVH-7/coefficients/export?model=static&format=px5", headers=VIEWER).status_code == 422
        assert c.get("/gyros/KVH-7/coefficients/export?model=static&format=px4").status_code == 401


def test_cli_exports_to_a_file_and_refuses_with_exit_code(stored, tmp_path):
    import os
    import sys

    _, url = stored
    env = {**os.environ, "BENCH_DATABASE_URL": url}
    out = tmp_path / "g.parm"
    r = subprocess.run([sys.executable, "-m", "bench", "coefficients", "KVH-7", "--model", "static", "--format",
                        "ardupilot", "-o", str(out)], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    assert parse_ardupilot(out.read_text())["INS_TCAL1_ENABLE"] == 1
    r = subprocess.run([sys.executable, "-m", "bench", "coefficients", "KVH-7", "--model", "dynamic", "--format",
                        "px4"], capture_output=True, text=True, env=env)
    assert r.returncode == 3 and "cannot export" in r.stderr and "dT/dt" in r.stderr and r.stdout == ""
