"""Fitted coefficients in the formats firmware reads: PX4 parameters, ArduPilot parameters, a C header.

Pure functions from ``FitResult`` objects (one per gyro channel) to text.  Each format has its own
evaluation convention; the export rewrites the product's model in it exactly (up to rounding), or
refuses with the reason when it cannot (``NotExpressible``).

Every linear model (``bench.fit.models``) is a sum of coefficient x term tree over input signals
(temperature, its rate, raw columns), each input clipped to its fitted range.  ``expand`` turns that
into a polynomial in the centred inputs ``u_i = x_i - centre_i``; the formats then read it.

* **PX4** (``Tools/process_sensor_caldata.py``, ``TemperatureCompensation::calc_thermal_offsets_*``,
  thermal-calibration docs): per gyro instance ``i`` and axis ``a`` (0, 1, 2 = x, y, z)
  ``offset = X0 + X1 d + X2 d^2 + X3 d^3`` with ``d = clip(T, TMIN, TMAX) - TREF`` in rad/s;
  ``corrected = raw - offset``.  Only a cubic (or lower) in one temperature fits; a model with rate,
  gradient or other column terms, or of degree > 3, is refused.  TREF is free: the product's own
  reference (``t0_c``) is used so the coefficients are the product's, converted to rad/s.  Written
  as a QGroundControl parameter file: ``vehicle<TAB>component<TAB>name<TAB>value<TAB>type`` (type 6
  = int32, 9 = float).
* **ArduPilot** (``libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp``,
  ``Tools/scripts/tempcal_IMU.py``): fixed reference 35 C; ``INS_TCALn_GYRk_<axis>`` are the k-th
  order coefficients (k = 1..3) in rad/s/C^k multiplied by 1e6; the constant term is not stored.
  The firmware applies ``gyro -= P(clamp(T) - 35) - P(clamp(caltemp) - 35)`` (no constant, clamp to
  TMIN..TMAX) and then subtracts the ordinary gyro offset ``INS_GYROFFS_*`` measured at
  ``INS_GYRn_CALTEMP``.  The export therefore also writes that offset: the product's bias at the
  calibration temperature (default 35 C, moved into TMIN..TMAX), so the chain reproduces the product;
  a boot-time gyro calibration replaces it with a fresh measurement, which is ArduPilot's design.
  Same refusals as PX4.  Written as ``NAME VALUE`` lines as ``tempcal_IMU.py`` does.
* **C header**: any linear model.  ``static const`` arrays (inputs, clip ranges, monomial exponents,
  coefficients per channel, convex-hull half planes) and ``static inline double
  <prefix>_bias_dph(int channel, const double in[], int *flagged)``; the caller supplies the inputs
  (temperatures in C, rates in C/min filtered as the header says).  Compiles with ``-Wall -Wextra``.

Units: the product's bias is in deg/h; PX4 and ArduPilot work in rad/s.

Public API::

    px4_params(gyro_id, results, *, instance=0, device_id=0, label="") -> str
    ardupilot_params(gyro_id, results, *, imu=1, caltemp_c=None, label="") -> str
    c_header(gyro_id, results, *, label="") -> str
    temperature_cubic(result, tref_c, fmt) -> TemperatureCubic
    expand(node, index, centres) -> {exponents: coefficient}
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from bench.errors import BenchError
from bench.fit.base import FitResult

DPH_PER_RADS = 180.0 / math.pi * 3600.0          # deg/h in one rad/s
ARDUPILOT_TREF_C = 35.0                           # AP_InertialSensor_tempcal.cpp TEMP_REFERENCE
ARDUPILOT_SCALE = 1.0e6                           # AP_InertialSensor_tempcal.cpp SCALE_FACTOR
AXES = ("x", "y", "z")
FORMATS = ("json", "px4", "ardupilot", "c-header")
HULL_TOL = 1e-6                                   # bench.fit.models.inside_hull default

Poly = dict[tuple[int, ...], float]


class NotExpressible(BenchError):
    """A model that a firmware format cannot express; the message gives the reason."""


# ----------------------------------------------------------------------------- polynomial algebra
def _p_add(a: Poly, b: Poly, sign: float = 1.0) -> Poly:
    out = dict(a)
    for k, v in b.items():
        out[k] = out.get(k, 0.0) + sign * v
    return out


def _p_mul(a: Poly, b: Poly) -> Poly:
    out: Poly = {}
    for ka, va in a.items():
        for kb, vb in b.items():
            k = tuple(x + y for x, y in zip(ka, kb))
            out[k] = out.get(k, 0.0) + va * vb
    return out


def expand(node: dict[str, Any], index: dict[str, int], centres: list[float]) -> Poly:
    """Polynomial of a term tree in the centred inputs ``u_i = x_i - centres[i]``; ``index`` maps the
    signal key (``temp:temp_t1``) to ``i``.  Keys of the result are exponent tuples."""
    n = len(centres)
    zero = (0,) * n
    op = node["op"]
    if op in ("temp", "rate", "column"):
        i = index[f"{op}:{node['column']}"]
        unit = tuple(1 if j == i else 0 for j in range(n))
        return {unit: 1.0, zero: float(centres[i])}
    if op == "const":
        return {zero: float(node["value"])}
    if op == "pow":
        base = expand(node["args"][0], index, centres)
        out: Poly = {zero: 1.0}
        for _ in range(int(node["exp"])):
            out = _p_mul(out, base)
        return out
    a, b = (expand(x, index, centres) for x in node["args"])
    if op == "add":
        return _p_add(a, b)
    if op == "sub":
        return _p_add(a, b, -1.0)
    if op == "mul":
        return _p_mul(a, b)
    raise NotExpressible(f"unknown term operation {op!r}")


def _leaves(node: dict[str, Any]) -> list[dict[str, Any]]:
    if node["op"] in ("temp", "rate", "column"):
        return [node]
    return [leaf for a in node.get("args", []) for leaf in _leaves(a)]


def _linear_terms(result: FitResult, fmt: str) -> list[dict[str, Any]]:
    d = result.definition
    if d.get("kind") != "linear" or "terms" not in d:
        raise NotExpressible(f"{fmt}: model {result.model!r} (channel {result.channel}) is not a model linear in "
                             f"its coefficients over term trees (kind {d.get('kind')!r}); only the JSON export "
                             f"carries it")
    if d.get("target_unit", "deg/h") != "deg/h":
        raise NotExpressible(f"{fmt}: model {result.model!r} predicts {d.get('target_unit')}, not a gyro bias in deg/h")
    return d["terms"]


def model_polynomial(result: FitResult, fmt: str, centres: dict[str, float] | None = None
                     ) -> tuple[list[str], list[float], Poly]:
    """(input keys, centres, bias polynomial in deg/h) of a linear FitResult.  Default centre of each
    input: the middle of its fitted range."""
    terms = _linear_terms(result, fmt)
    ranges = result.validity.get("signals", {})
    keys: list[str] = []
    for t in terms:
        for leaf in _leaves(t["tree"]):
            k = f"{leaf['op']}:{leaf['column']}"
            if k not in keys:
                keys.append(k)
    cvals = []
    for k in keys:
        if centres and k in centres:
            cvals.append(float(centres[k]))
        elif k in ranges:
            cvals.append(0.5 * (ranges[k][0] + ranges[k][1]))
        else:
            cvals.append(0.0)
    index = {k: i for i, k in enumerate(keys)}
    total: Poly = {}
    for t in terms:
        value = float(result.coefficients[t["coefficient"]])
        total = _p_add(total, {e: value * c for e, c in expand(t["tree"], index, cvals).items()})
    return keys, cvals, total


# ---------------------------------------------------------------------------- one-temperature cubic
@dataclass(frozen=True)
class TemperatureCubic:
    """bias_dph(T) = sum_k coef_dph[k] (clip(T, tmin, tmax) - tref)^k, k = 0..3."""
    key: str
    column: str
    tref_c: float
    tmin_c: float
    tmax_c: float
    coef_dph: tuple[float, float, float, float]

    def bias_dph(self, temp_c: np.ndarray) -> np.ndarray:
        d = np.clip(np.asarray(temp_c, float), self.tmin_c, self.tmax_c) - self.tref_c
        c = self.coef_dph
        return c[0] + d * (c[1] + d * (c[2] + d * c[3]))


def temperature_cubic(result: FitResult, tref_c: float | None, fmt: str) -> TemperatureCubic:
    """The model as a cubic in one clipped temperature about ``tref_c`` (None: the model's own t0_c, else
    the middle of the fitted range), or ``NotExpressible`` naming the term that prevents it."""
    terms = _linear_terms(result, fmt)
    temps: list[str] = []
    for t in terms:
        for leaf in _leaves(t["tree"]):
            if leaf["op"] != "temp":
                what = {"rate": "a temperature-rate (dT/dt)", "column": "a non-temperature column"}[leaf["op"]]
                raise NotExpressible(
                    f"{fmt}: model {result.model!r} channel {result.channel}: term {t['coefficient']} = {t['expr']} "
                    f"uses {what} input ({leaf['column']}); {fmt} compensates with a polynomial in one temperature only")
            if leaf["column"] not in temps:
                temps.append(leaf["column"])
    if len(temps) > 1:
        raise NotExpressible(f"{fmt}: model {result.model!r} channel {result.channel} uses {len(temps)} temperatures "
                             f"({', '.join(temps)}: a gradient term); {fmt} compensates with one sensor temperature")
    if not temps:
        raise NotExpressible(f"{fmt}: model {result.model!r} channel {result.channel} has no temperature input")
    key = f"temp:{temps[0]}"
    rng = result.validity.get("signals", {}).get(key)
    if not rng:
        raise NotExpressible(f"{fmt}: model {result.model!r} channel {result.channel} has no fitted range for {key}")
    if tref_c is None:
        t0 = result.definition.get("t0_c")
        tref_c = float(t0) if isinstance(t0, (int, float)) else 0.5 * (rng[0] + rng[1])
    keys, _, poly = model_polynomial(result, fmt, {key: tref_c})
    coef = [0.0, 0.0, 0.0, 0.0]
    for e, c in poly.items():
        deg = e[0] if e else 0
        if deg > 3:
            if c != 0.0:
                raise NotExpressible(f"{fmt}: model {result.model!r} channel {result.channel} is of degree {deg} in "
                                     f"{temps[0]}; {fmt} holds a cubic at most")
            continue
        coef[deg] += c
    return TemperatureCubic(key, temps[0], float(tref_c), float(rng[0]), float(rng[1]), tuple(coef))


def _by_axis(results: list[FitResult], fmt: str) -> dict[int, FitResult]:
    out: dict[int, FitResult] = {}
    for r in results:
        if r.channel not in AXES:
            raise NotExpressible(f"{fmt}: channel {r.channel!r} is not one of the gyro axes x, y, z")
        if AXES.index(r.channel) in out:
            raise NotExpressible(f"{fmt}: two fits for channel {r.channel}")
        out[AXES.index(r.channel)] = r
    if not out:
        raise NotExpressible(f"{fmt}: no channel to export")
    return out


def _common_cubics(results: list[FitResult], fmt: str, tref_c: float | None) -> dict[int, TemperatureCubic]:
    """One cubic per axis on one temperature with one clip range (the firmware has one per sensor)."""
    axes = _by_axis(results, fmt)
    first = temperature_cubic(axes[min(axes)], tref_c, fmt)
    out = {}
    for a, r in sorted(axes.items()):
        cub = temperature_cubic(r, first.tref_c, fmt)
        if cub.column != first.column:
            raise NotExpressible(f"{fmt}: channel {AXES[a]} is compensated with {cub.column} but channel "
                                 f"{AXES[min(axes)]} with {first.column}; {fmt} uses one temperature per gyro")
        if (cub.tmin_c, cub.tmax_c) != (first.tmin_c, first.tmax_c):
            raise NotExpressible(
                f"{fmt}: channel {AXES[a]} is valid over {cub.tmin_c:g}..{cub.tmax_c:g} C but channel {AXES[min(axes)]} "
                f"over {first.tmin_c:g}..{first.tmax_c:g} C; {fmt} has one TMIN/TMAX per gyro (refit the channels "
                f"on the same data)")
        out[a] = cub
    return out


def _num(v: float) -> str:
    return repr(float(v))


def _head(lines: list[str], prefix: str, gyro_id: str, label: str, cub: TemperatureCubic, missing: list[str]) -> None:
    lines.append(f"{prefix} gyrobench: gyro {gyro_id}{', ' + label if label else ''}")
    lines.append(f"{prefix} temperature input: {cub.column} (C) - the firmware uses the sensor's own temperature, "
                 f"which must track this probe")
    lines.append(f"{prefix} valid {cub.tmin_c!r}..{cub.tmax_c!r} C; the firmware clips the temperature to this range")
    if missing:
        lines.append(f"{prefix} axes {', '.join(missing)} were not fitted: zero coefficients (no compensation)")


# ------------------------------------------------------------------------------------------ PX4
def px4_params(gyro_id: str, results: list[FitResult], *, instance: int = 0, device_id: int = 0,
               label: str = "", vehicle_id: int = 1, component_id: int = 1) -> str:
    """QGroundControl parameter file with PX4's ``TC_G<instance>_*`` gyro thermal compensation."""
    if not 0 <= instance <= 3:
        raise NotExpressible(f"px4: gyro instance {instance} not in 0..3")
    if not -2**31 <= device_id < 2**31:
        raise NotExpressible(f"px4: device id {device_id} does not fit an int32 parameter")
    cubics = _common_cubics(results, "px4", None)
    any_cub = next(iter(cubics.values()))
    g = f"TC_G{instance}"
    lines = ["# PX4 sensor thermal compensation parameters (gyro)"]
    _head(lines, "#", gyro_id, label, any_cub, [AXES[a] for a in range(3) if a not in cubics])
    lines += ["# offset = X0 + X1*d + X2*d^2 + X3*d^3 [rad/s], d = clip(T, TMIN, TMAX) - TREF; corrected = raw - offset",
              f"# {g}_ID must be the gyro's device id (CAL_GYRO{instance}_ID) for PX4 to apply these",
              "#", "# Vehicle-Id Component-Id Name Value Type"]

    def row(name: str, value: str, ptype: int) -> None:
        lines.append(f"{vehicle_id}\t{component_id}\t{name}\t{value}\t{ptype}")

    row("TC_G_ENABLE", "1", 6)
    row(f"{g}_ID", str(int(device_id)), 6)
    row(f"{g}_TMAX", _num(any_cub.tmax_c), 9)
    row(f"{g}_TMIN", _num(any_cub.tmin_c), 9)
    row(f"{g}_TREF", _num(any_cub.tref_c), 9)
    for k in range(4):
        for a in range(3):
            c = cubics[a].coef_dph[k] / DPH_PER_RADS if a in cubics else 0.0
            row(f"{g}_X{k}_{a}", _num(c), 9)
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------ ArduPilot
def ardupilot_params(gyro_id: str, results: list[FitResult], *, imu: int = 1, caltemp_c: float | None = None,
                     label: str = "") -> str:
    """ArduPilot ``INS_TCAL<imu>_*`` parameters plus the gyro offsets at the calibration temperature."""
    if not 1 <= imu <= 3:
        raise NotExpressible(f"ardupilot: IMU {imu} not in 1..3")
    cubics = _common_cubics(results, "ardupilot", ARDUPILOT_TREF_C)
    any_cub = next(iter(cubics.values()))
    cal = ARDUPILOT_TREF_C if caltemp_c is None else float(caltemp_c)
    cal = min(max(cal, any_cub.tmin_c), any_cub.tmax_c)        # the firmware clamps it the same way
    t = f"INS_TCAL{imu}"
    offs = "INS_GYROFFS" if imu == 1 else f"INS_GYR{imu}OFFS"
    lines = ["# ArduPilot IMU temperature calibration (gyro)"]
    _head(lines, "#", gyro_id, label, any_cub, [AXES[a] for a in range(3) if a not in cubics])
    lines += ["# correction: gyro -= P(clamp(T)-35) - P(clamp(CALTEMP)-35); gyro -= GYROFFS; "
              "P(e) = (GYR1 e + GYR2 e^2 + GYR3 e^3) * 1e-6 [rad/s]",
              f"# {offs}_* = the bias at INS_GYR{imu}_CALTEMP = {cal!r} C (the constant part, rad/s); a boot-time "
              "gyro calibration replaces it with a fresh measurement",
              f"# the accelerometer terms {t}_ACC* are left as they are"]
    lines.append(f"{t}_ENABLE 1")
    lines.append(f"{t}_TMIN {_num(any_cub.tmin_c)}")
    lines.append(f"{t}_TMAX {_num(any_cub.tmax_c)}")
    for k in range(1, 4):
        for a, ax in enumerate(AXES):
            c = cubics[a].coef_dph[k] / DPH_PER_RADS * ARDUPILOT_SCALE if a in cubics else 0.0
            lines.append(f"{t}_GYR{k}_{ax.upper()} {_num(c)}")
    for a, ax in enumerate(AXES):
        off = float(cubics[a].bias_dph(np.array([cal]))[0]) / DPH_PER_RADS if a in cubics else 0.0
        lines.append(f"{offs}_{ax.upper()} {_num(off)}")
    lines.append(f"INS_GYR{imu}_CALTEMP {_num(cal)}")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------- C header
def _c_ident(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower()
    return ("g_" + s) if not s or s[0].isdigit() else s


def _c_num(v: float) -> str:
    if not math.isfinite(v):
        raise NotExpressible(f"c-header: non-finite number {v!r}")
    return repr(float(v))


def _hull_planes(vertices: list[list[float]]) -> tuple[list[float], list[float], list[list[float]]]:
    """The product's hull test (``models.inside_hull``): scale lo/span and half-plane equations."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    h = ConvexHull((v - lo) / span)
    return lo.tolist(), span.tolist(), h.equations.tolist()


def c_header(gyro_id: str, results: list[FitResult], *, label: str = "") -> str:
    """A self-contained C99 header evaluating the model's bias for each channel."""
    if not results:
        raise NotExpressible("c-header: no channel to export")
    model = results[0].model
    prefix = _c_ident(f"gb_{gyro_id}_{model}")
    up = prefix.upper()
    per = []
    keys: list[str] = []
    for r in results:
        k, _, _ = model_polynomial(r, "c-header")
        per.append(r)
        keys += [x for x in k if x not in keys]
    ranges_all = [r.validity.get("signals", {}) for r in per]
    centres = {}
    for k in keys:
        los = [rg[k][0] for rg in ranges_all if k in rg]
        his = [rg[k][1] for rg in ranges_all if k in rg]
        centres[k] = 0.5 * (min(los) + max(his)) if los else 0.0
    polys = []
    for r in per:
        k, c, p = model_polynomial(r, "c-header", centres)
        idx = [keys.index(x) for x in k]
        full: Poly = {}
        for e, v in p.items():
            fe = [0] * len(keys)
            for j, ex in zip(idx, e):
                fe[j] = ex
            full[tuple(fe)] = full.get(tuple(fe), 0.0) + v
        polys.append(full)
    monos = sorted({e for p in polys for e in p}, key=lambda e: (sum(e), tuple(-x for x in e)))
    if any(x > 255 for e in monos for x in e):
        raise NotExpressible("c-header: an exponent above 255")
    nin, nch, nmon = max(len(keys), 1), len(per), max(len(monos), 1)

    # inputs described from the first channel that has them
    desc = {}
    for r in per:
        for t in r.definition["terms"]:
            for leaf in _leaves(t["tree"]):
                desc.setdefault(f"{leaf['op']}:{leaf['column']}", leaf)
    window = {r.definition.get("rate_filter", {}).get("window_s") for r in per}
    lines = [f"/* {prefix}.h - gyro thermal compensation generated by gyrobench; do not edit.",
             f" * gyro {gyro_id}, model {model}{', ' + label if label else ''}",
             " *",
             f" * {prefix}_bias_dph(channel, in, &flagged) returns the predicted gyro bias in deg/h for channel",
             f" * {', '.join(f'{i} = {r.channel}' for i, r in enumerate(per))}; compensated rate = raw rate (deg/h) - bias.",
             " * in[] holds the inputs below.  Each input the channel uses is clipped to its fitted range; flagged is",
             " * set to 1 when an input was clipped or (T, dT/dt) lies outside the fitted convex hull.",
             " *",
             " * inputs:"]
    for i, k in enumerate(keys):
        leaf = desc[k]
        if leaf["op"] == "temp":
            what = f"temperature {leaf['column']} in C"
        elif leaf["op"] == "rate":
            what = (f"dT/dt of {leaf['column']} in C/min: centred least-squares slope over {sorted(window)[0]:g} s "
                    "(a causal estimate over the last window lags by half the window)")
        else:
            what = f"column {leaf['column']}"
        lines.append(f" *   in[{i}] {k} ({leaf.get('signal', '')}): {what}")
    lines += [" *", " * bias = sum over m of coef[channel][m] * prod over i of (in_clipped[i] - centre[i])^exp[m][i]",
              " */", f"#ifndef {up}_H", f"#define {up}_H", "", "#include <math.h>", "",
              f"#define {up}_N_INPUTS {nin}", f"#define {up}_N_CHANNELS {nch}", f"#define {up}_N_MONOMIALS {nmon}"]
    for i, r in enumerate(per):
        lines.append(f"#define {up}_CHANNEL_{_c_ident(r.channel).upper()} {i}")
    lines.append("")

    def arr(values: list[str]) -> str:
        return "{" + ", ".join(values) + "}"

    cvals = [_c_num(centres[k]) for k in keys] or ["0.0"]
    lines.append(f"static const double {prefix}_centre[{nin}] = {arr(cvals)};")
    uses, lo_rows, hi_rows = [], [], []
    for r, rg in zip(per, ranges_all):
        k_r, _, _ = model_polynomial(r, "c-header")
        uses.append(arr(["1" if k in k_r and k in rg else "0" for k in keys] or ["0"]))
        lo_rows.append(arr([_c_num(rg[k][0]) if k in rg else "0.0" for k in keys] or ["0.0"]))
        hi_rows.append(arr([_c_num(rg[k][1]) if k in rg else "0.0" for k in keys] or ["0.0"]))
    lines.append(f"static const unsigned char {prefix}_clipped[{nch}][{nin}] = {arr(uses)};")
    lines.append(f"static const double {prefix}_clip_lo[{nch}][{nin}] = {arr(lo_rows)};")
    lines.append(f"static const double {prefix}_clip_hi[{nch}][{nin}] = {arr(hi_rows)};")
    exps = [arr([str(x) for x in e] or ["0"]) for e in monos] or [arr(["0"] * nin)]
    lines.append(f"static const unsigned char {prefix}_exp[{nmon}][{nin}] = {arr(exps)};")
    coef_rows = [arr([_c_num(p.get(e, 0.0)) for e in monos] or ["0.0"]) for p in polys]
    lines.append(f"static const double {prefix}_coef[{nch}][{nmon}] = {arr(coef_rows)};")
    # convex hull of (T, dT/dt) per channel: scaled p = (x - lo) / span; outside if eq0 p0 + eq1 p1 + eq2 > tol
    hull_in, hull_lo, hull_span, first, count, eqs = [], [], [], [], [], []
    for r in per:
        verts = r.validity.get("hull")
        if verts:
            kt, kr = r.validity["hull_signals"]
            if kt not in keys or kr not in keys:
                raise NotExpressible(f"c-header: channel {r.channel}: hull inputs {kt}, {kr} are not model inputs")
            lo, span, eq = _hull_planes(verts)
            hull_in.append(arr([str(keys.index(kt)), str(keys.index(kr))]))
            hull_lo.append(arr([_c_num(x) for x in lo]))
            hull_span.append(arr([_c_num(x) for x in span]))
            first.append(str(len(eqs)))
            count.append(str(len(eq)))
            eqs += [arr([_c_num(x) for x in e]) for e in eq]
        else:
            hull_in.append(arr(["-1", "-1"]))
            hull_lo.append(arr(["0.0", "0.0"]))
            hull_span.append(arr(["1.0", "1.0"]))
            first.append("0")
            count.append("0")
    neq = max(len(eqs), 1)
    lines.append(f"static const int {prefix}_hull_inputs[{nch}][2] = {arr(hull_in)};")
    lines.append(f"static const double {prefix}_hull_lo[{nch}][2] = {arr(hull_lo)};")
    lines.append(f"static const double {prefix}_hull_span[{nch}][2] = {arr(hull_span)};")
    lines.append(f"static const int {prefix}_hull_first[{nch}] = {arr(first)};")
    lines.append(f"static const int {prefix}_hull_count[{nch}] = {arr(count)};")
    lines.append(f"static const double {prefix}_hull_eq[{neq}][3] = {arr(eqs or [arr(['0.0', '0.0', '0.0'])])};")
    lines += ["", f"static inline double {prefix}_bias_dph(int channel, const double in[{up}_N_INPUTS], int *flagged)",
              "{",
              f"    double u[{up}_N_INPUTS];",
              "    double bias = 0.0;",
              "    int i, m, e, h;",
              "    *flagged = 0;",
              f"    if (channel < 0 || channel >= {up}_N_CHANNELS) {{",
              "        *flagged = 1;",
              "        return NAN;",
              "    }",
              f"    for (i = 0; i < {up}_N_INPUTS; i++) {{",
              "        double x = in[i];",
              f"        if ({prefix}_clipped[channel][i]) {{",
              f"            if (x < {prefix}_clip_lo[channel][i]) {{ x = {prefix}_clip_lo[channel][i]; *flagged = 1; }}",
              f"            if (x > {prefix}_clip_hi[channel][i]) {{ x = {prefix}_clip_hi[channel][i]; *flagged = 1; }}",
              "        }",
              f"        u[i] = x - {prefix}_centre[i];",
              "    }",
              f"    for (m = 0; m < {up}_N_MONOMIALS; m++) {{",
              f"        double term = {prefix}_coef[channel][m];",
              "        if (term == 0.0) {",
              "            continue;           /* another channel's monomial */",
              "        }",
              f"        for (i = 0; i < {up}_N_INPUTS; i++) {{",
              f"            for (e = 0; e < {prefix}_exp[m][i]; e++) {{",
              "                term *= u[i];",
              "            }",
              "        }",
              "        bias += term;",
              "    }",
              f"    if ({prefix}_hull_count[channel] > 0) {{",
              f"        const double t = in[{prefix}_hull_inputs[channel][0]];",
              f"        const double r = in[{prefix}_hull_inputs[channel][1]];",
              "        if (isfinite(t) && isfinite(r)) {",
              f"            const double p0 = (t - {prefix}_hull_lo[channel][0]) / {prefix}_hull_span[channel][0];",
              f"            const double p1 = (r - {prefix}_hull_lo[channel][1]) / {prefix}_hull_span[channel][1];",
              f"            for (h = {prefix}_hull_first[channel]; h < {prefix}_hull_first[channel] + "
              f"{prefix}_hull_count[channel]; h++) {{",
              f"                if ({prefix}_hull_eq[h][0] * p0 + {prefix}_hull_eq[h][1] * p1 + {prefix}_hull_eq[h][2] "
              f"> {HULL_TOL!r}) {{",
              "                    *flagged = 1;",
              "                    break;",
              "                }",
              "            }",
              "        }",
              "    }",
              "    return bias;",
              "}",
              "", f"#endif /* {up}_H */", ""]
    return "\n".join(lines)


def render(fmt: str, gyro_id: str, results: list[FitResult], *, label: str = "", options: dict[str, Any] | None = None
           ) -> tuple[str, str, str]:
    """(text, media type, file suffix) of ``results`` (one model, one FitResult per channel) in ``fmt``."""
    opts = options or {}
    if fmt == "px4":
        return (px4_params(gyro_id, results, instance=int(opts.get("px4_instance", 0)),
                           device_id=int(opts.get("px4_device_id", 0)), label=label), "text/plain", ".params")
    if fmt == "ardupilot":
        return (ardupilot_params(gyro_id, results, imu=int(opts.get("ardupilot_imu", 1)),
                                 caltemp_c=opts.get("ardupilot_caltemp_c"), label=label), "text/plain", ".parm")
    if fmt == "c-header":
        return c_header(gyro_id, results, label=label), "text/x-c", ".h"
    if fmt == "json":
        import json

        from bench.fit.export import build_export
        doc = build_export(gyro_id, results, source={"label": label} if label else None)
        return json.dumps(doc, indent=2, allow_nan=False) + "\n", "application/json", ".json"
    raise NotExpressible(f"unknown format {fmt!r} (use one of {', '.join(FORMATS)})")


__all__ = ["FORMATS", "NotExpressible", "TemperatureCubic", "ardupilot_params", "c_header", "expand",
           "model_polynomial", "px4_params", "render", "temperature_cubic"]
