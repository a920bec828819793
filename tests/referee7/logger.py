"""Referee 7 logger: turns 1-s physical truth into what a lab logger writes, and writes CSV v1.

Conventions:

* ``LogSpec`` describes one logger set-up: ``period`` (0.5, 1, 2 or 10 s), ``average`` (True: each row
  is the mean of the 1-s values inside its period, as a 10-s averaging logger does), ``epoch`` (time_s
  as Unix seconds ~1.8e9), ``jitter_s`` (timestamp jitter std), ``gaps`` (number of 3-6 min logger
  outages), ``p_missing`` (chance that one probe cell is empty).
* Probes read like a DS18B20: a fixed per-probe calibration offset, 0.02 C read noise, 0.0625 C steps,
  one conversion per second (0.5-s rows repeat the last conversion).
* Gyro white noise is drawn at the row rate (std 60*ARW/sqrt(period)); slow noise and the bias are
  taken from the 1-s truth; the output is quantised to the unit's count size before averaging.
* ``Rows.at(x)`` maps any 1-s truth array onto the logged rows exactly as the logger did (the oracle
  uses it for the true effect columns).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DS_STEP = 0.0625


@dataclass
class LogSpec:
    period: float = 1.0
    average: bool = False
    epoch: bool = False
    jitter_s: float = 0.0
    gaps: int = 0
    p_missing: float = 0.0


class Rows:
    """Row instants (s since run start) and the mapping from the 1-s grid onto them."""

    def __init__(self, n1: int, spec: LogSpec, rng):
        p = spec.period
        if spec.average:
            m = int(round(p))
            nb = n1 // m
            self.blocks = (nb, m)
            inst = np.arange(nb) * p + (p - 1) / 2.0 + 0.5     # centre of the block
        else:
            self.blocks = None
            inst = np.arange(0.0, n1 - 1, p)
        keep = np.ones(len(inst), bool)
        for _ in range(spec.gaps):
            g0 = rng.uniform(0.15, 0.85) * inst[-1]
            keep &= ~((inst >= g0) & (inst < g0 + rng.uniform(180, 360)))
        self.keep = keep
        self.t = inst[keep]
        self.period = p

    def at(self, x: np.ndarray) -> np.ndarray:
        if self.blocks is not None:
            nb, m = self.blocks
            return x[:nb * m].reshape(nb, m).mean(axis=1)[self.keep]
        return np.interp(self.t, np.arange(len(x)), x)


def probe_readings(T: np.ndarray, offset: float, rows: Rows, spec: LogSpec, rng) -> np.ndarray:
    """DS18B20 conversions once per second, then held / averaged / sampled like the logger."""
    conv = np.round((T + offset + rng.normal(0, 0.02, len(T))) / DS_STEP) * DS_STEP
    if rows.blocks is not None:
        vals = rows.at(conv)
    else:
        vals = conv[np.minimum(np.floor(rows.t).astype(int), len(T) - 1)]   # last conversion
    if spec.p_missing > 0:
        vals = vals.copy()
        vals[rng.random(len(vals)) < spec.p_missing] = np.nan
    return vals


def gyro_readings(truth1: np.ndarray, slow_noise1: np.ndarray, arw: float, count: float,
                  rows: Rows, rng) -> np.ndarray:
    if rows.blocks is not None:        # average 1-s quantised outputs
        w1 = arw * 60.0 * rng.standard_normal(len(truth1))
        q = np.round((truth1 + slow_noise1 + w1) / count) * count
        return rows.at(q)
    w = arw * 60.0 / np.sqrt(rows.period) * rng.standard_normal(len(rows.t))
    return np.round((rows.at(truth1 + slow_noise1) + w) / count) * count


def timestamps(rows: Rows, spec: LogSpec, rng) -> np.ndarray:
    t = rows.t.copy()
    if spec.jitter_s > 0:
        t = t + np.clip(rng.normal(0, spec.jitter_s, len(t)), -0.2 * rows.period, 0.2 * rows.period)
    if spec.epoch:
        t = t + 1.8e9 + float(rng.integers(0, 3e7))
    return t


def write_csv(path, meta: dict, cols: dict) -> None:
    """CSV v1 with our own formatting: 3 decimals for time, 4 for temperatures, 5 for gyro."""
    names = list(cols)
    fmts = []
    for nm in names:
        fmts.append("%.3f" if nm == "time_s" else "%.4f" if nm.startswith("temp_")
                    else "%d" if nm == "power" else "%.5f")
    n = len(cols["time_s"])
    lines = [f"# {k}: {v}" for k, v in meta.items()]
    lines.append(",".join(names))
    arrs = [cols[nm] for nm in names]
    for i in range(n):
        cells = []
        for a, f in zip(arrs, fmts):
            v = a[i]
            cells.append("" if not np.isfinite(v) else f % v)
        lines.append(",".join(cells))
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
