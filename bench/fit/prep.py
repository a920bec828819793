"""Data preparation: outliers, averaging, temperature rates, gradients, Earth rate, axes, eight-position.

Pure functions over numpy arrays / ``Dataset``; no I/O.  Sources:

* Pauta (3-sigma, 拉依达准则) rejection, applied to residuals or short windows only, never to a
  trending raw signal (calibration-notes 4.1 "Outliers"; S000 3.3).
* 100-s averaging ("百秒标准差", S000 Table 3) -> ``block_average``.
* dT/dt in C/min (S000 eq 4 unit of q; S001 defines a forward difference over a set interval):
  ``bench.signal.temperature_rate`` with the ``"centred_slope"`` method (centred least-squares slope
  over ``window_s`` seconds; calibration-notes lesson 9).
* Earth rate and orientation geometry: ``bench.signal.geometry`` (default code ``NUE`` = S000's 北天东).
* Installation matrix M (S000 eq 1): omega_system = M @ omega_channel; channel axis i in the system
  frame = row i of inv(M), so Earth rate read by channel i = (inv(M) @ Omega_body)_i (S000 eq 2).
* Eight-position test (S000 3.2): positions ESD, USE, WSU, DSW, WND, UNW, ENU, DNE; per-position
  means y_k = b + A @ Omega_body,k, solved by least squares for bias b and A = inv(M).
* Bin-averaging by temperature (calibration-notes lesson 1; PX4 / ArduPilot 0.5 C bins).

Public API::

    pauta_mask(x, *, time=None, window_s=None, n_sigma=3.0, max_iter=10) -> bool array (True = keep)
    screen_glitches(ds) -> (Dataset with isolated glitches of gyro_* / freq_* / temp_* set missing, {column: found})
    block_average(ds, period_s=100.0, *, min_fraction=0.5) -> Dataset
    rate_c_per_min(time_s, temp_c, window_s=DEFAULT_RATE_WINDOW_S) -> array (C/min)
    add_rates(ds, window_s=DEFAULT_RATE_WINDOW_S, names=None) -> Dataset  (adds rate_<name> columns)
    gradient(ds, a, b) -> array   (temp_a - temp_b)
    bin_by_temperature(temp, *ys, bin_c=0.5, min_count=1) -> (t_mean, [y_means], counts)
    bin_dataset_by_temperature(ds, probe, bin_c=0.5, min_count=1) -> Dataset
    orientation_axes(code) -> (3,3) rows = body x,y,z unit vectors in ENU
    earth_rate_enu(lat_deg) -> (3,)
    earth_rate_body(code, lat_deg) -> (3,)
    earth_rate_reading(ds, channel, latitude_deg=None, axis=None) -> array (deg/h, per sample)
    remove_earth_rate(ds, latitude_deg=None, axes=None) -> Dataset  (gyro_<ch> minus Earth rate)
    channel_axes_from_m(m) -> (3,3) ;  to_system_axes(ds, m, channels, out) / to_channel_axes(...)
    eight_position(ds, channels, latitude_deg=None, settle_s=0.0) -> EightPositionResult
    EIGHT_POSITIONS = ("ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.errors import DataFormatError
from bench.fit.base import Dataset
from bench.fit.csvio import ORIENTATION_DEFAULT
from bench.signal import (  # noqa: F401  (earth_rate_enu / orientation_axes: re-exported for callers)
    EARTH_RATE_DPH,
    block_means,
    earth_rate_body,
    earth_rate_body_per_sample,
    earth_rate_enu,
    isolated_glitches,
    orientation_axes,
    run_segments,
    temperature_rate,
)

_BODY = {"x": 0, "y": 1, "z": 2}

DEFAULT_RATE_WINDOW_S = 120.0
EIGHT_POSITIONS = ("ESD", "USE", "WSU", "DSW", "WND", "UNW", "ENU", "DNE")

# ----------------------------------------------------------------------------------------- outliers
def pauta_mask(x: np.ndarray, *, time: np.ndarray | None = None, window_s: float | None = None,
               n_sigma: float = 3.0, max_iter: int = 10) -> np.ndarray:
    """Pauta criterion: True where |x - mean| <= n_sigma * std (iterated until nothing changes).

    Apply to residuals (``window_s=None``: one global mean/std) or to a raw signal in short windows
    (``time`` and ``window_s`` given: mean/std per consecutive window of ``window_s`` seconds).
    NaN samples are never kept.
    """
    x = np.asarray(x, dtype=np.float64)
    keep = np.isfinite(x)
    if window_s is None:
        for _ in range(max_iter):
            if keep.sum() < 3:
                break
            mean, sd = x[keep].mean(), x[keep].std(ddof=1)
            new_keep = keep & (np.abs(x - mean) <= n_sigma * sd)
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        return keep
    if time is None:
        raise ValueError("pauta_mask: window_s needs time")
    t = np.asarray(time, dtype=np.float64)
    groups = np.floor((t - t[0]) / float(window_s)).astype(np.int64)
    ng = int(groups.max()) + 1 if len(groups) else 0
    for _ in range(max_iter):
        w = keep.astype(np.float64)
        xv = np.where(keep, x, 0.0)
        cnt = np.bincount(groups, w, ng)
        s1 = np.bincount(groups, xv, ng)
        mean = s1 / np.maximum(cnt, 1)
        dev = np.where(keep, x - mean[groups], 0.0)
        var = np.bincount(groups, dev * dev, ng) / np.maximum(cnt - 1, 1)
        sd = np.sqrt(var)
        new_keep = keep & (np.abs(x - mean[groups]) <= n_sigma * sd[groups])
        new_keep |= keep & (cnt[groups] < 3)         # too few samples to judge
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return keep


# the columns screened (gyro outputs, HRG resonance frequencies, probes), with the least deviation a
# glitch must have there: a probe glued to a unit does not leave its course by a degree for one reading
# (a DS18B20's power-on 85.0 C, a 127.94 C bus error), while its readings averaged over a logging
# period leave it by 0.03 C at 8 robust sigmas
GLITCH_MIN_DEVIATION = {"gyro_": 0.0, "freq_": 0.0, "temp_": 1.0}
GLITCH_TIMES_REPORTED = 5


# columns that set the conditions of a stretch of the record: where one changes, a new piece begins
CONDITION_COLUMNS = ("orientation", "table_rate_dps", "power")


def _condition_pieces(ds: Dataset) -> np.ndarray | None:
    """A piece number per sample that steps wherever a ``CONDITION_COLUMNS`` column changes value."""
    change = np.zeros(max(len(ds) - 1, 0), dtype=bool)
    present = [c for c in CONDITION_COLUMNS if c in ds]
    for name in present:
        col = np.asarray(ds[name])
        if col.dtype.kind in "fc":
            a, b = col[1:], col[:-1]
            change |= (a != b) & ~(np.isnan(a) & np.isnan(b))
        else:
            change |= col[1:].astype(str) != col[:-1].astype(str)
    return np.concatenate([[0], np.cumsum(change)]) if present else None


def screen_glitches(ds: Dataset) -> tuple[Dataset, dict[str, dict[str, object]]]:
    """Isolated glitches (``bench.signal.isolated_glitches``: a corrupted gyro frame, a probe's 85.0 C
    power-on reading) of every ``gyro_*``, ``freq_*`` and ``temp_*`` column set missing, as a failed
    reading is; each stretch of steady conditions (a multi-position test's position, a turntable rate,
    the power state: ``CONDITION_COLUMNS``) is judged on its own.  Returns the screened dataset and,
    per column that had any, ``{"samples": n, "time_s": [the first few]}``; a dataset without
    glitches is returned as it is."""
    found: dict[str, dict[str, object]] = {}
    cols: dict[str, np.ndarray] = {}
    labels = _condition_pieces(ds)
    for name, col in ds.columns.items():
        prefix = next((p for p in GLITCH_MIN_DEVIATION if name.startswith(p)), None)
        if prefix is None:
            continue
        x = np.asarray(col, dtype=np.float64)
        bad = isolated_glitches(ds.time, x, GLITCH_MIN_DEVIATION[prefix], labels)
        if bad.any():
            cols[name] = np.where(bad, np.nan, x)
            found[name] = {"samples": int(bad.sum()),
                           "time_s": [float(t) for t in ds.time[bad][:GLITCH_TIMES_REPORTED]]}
    return (ds.with_columns(**cols) if cols else ds), found


# ---------------------------------------------------------------------------------------- averaging
def block_average(ds: Dataset, period_s: float = 100.0, *, min_fraction: float = 0.5) -> Dataset:
    """Average every numeric column over consecutive ``period_s`` blocks (``bench.signal.block_means``:
    aligned on the first sample of each piece of the record, a piece ending where ``orientation``
    changes; NaNs ignored per column; blocks with fewer than ``min_fraction`` of the piece's usual
    sample count dropped).  ``time_s`` becomes the mean time of the samples in the block;
    ``orientation`` the code of the block.  ``meta['average_s']`` is set."""
    if len(ds) == 0:
        return ds
    labels = np.asarray(ds["orientation"]) if "orientation" in ds else None
    segments = run_segments(ds.time, labels, gap_factor=np.inf)
    numeric = {name: col for name, col in ds.columns.items() if name != "orientation"}
    res = block_means(ds.time, numeric, float(period_s), segments, min_fraction=min_fraction)
    cols: dict[str, np.ndarray] = {}
    for name in ds.columns:
        cols[name] = np.asarray(ds["orientation"])[res.first_index] if name == "orientation" else res.columns[name]
    meta = dict(ds.meta)
    meta["average_s"] = repr(float(period_s))
    return Dataset(cols, meta)


def bin_by_temperature(temp: np.ndarray, *ys: np.ndarray, bin_c: float = 0.5,
                       min_count: int = 1) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Average ``ys`` in equal-width temperature bins of ``bin_c`` (calibration-notes lesson 1).

    Returns (mean temperature per bin, [mean of each y per bin], sample count per bin); empty bins and
    bins with fewer than ``min_count`` samples are dropped.  Samples with NaN anywhere are ignored."""
    temp = np.asarray(temp, dtype=np.float64)
    ok = np.isfinite(temp)
    for y in ys:
        ok &= np.isfinite(np.asarray(y, dtype=np.float64))
    tt = temp[ok]
    if tt.size == 0:
        return np.array([]), [np.array([]) for _ in ys], np.array([], dtype=np.int64)
    idx = np.floor((tt - tt.min()) / bin_c).astype(np.int64)
    nb = int(idx.max()) + 1
    cnt = np.bincount(idx, minlength=nb)
    good = cnt >= max(1, min_count)
    tm = np.bincount(idx, tt, nb)[good] / cnt[good]
    means = [np.bincount(idx, np.asarray(y, dtype=np.float64)[ok], nb)[good] / cnt[good] for y in ys]
    return tm, means, cnt[good]


def bin_dataset_by_temperature(ds: Dataset, probe: str, bin_c: float = 0.5, min_count: int = 1) -> Dataset:
    """``Dataset`` of per-bin means of every numeric column, binned on ``temp_<probe>``.

    A sample is used when ``temp_<probe>`` is finite; other columns are averaged over their finite
    values in the bin (NaN when a bin has none).  ``orientation`` is dropped (bins mix positions)."""
    temp = np.asarray(ds[f"temp_{probe}"], dtype=np.float64)
    ok = np.isfinite(temp)
    tt = temp[ok]
    if tt.size == 0:
        raise DataFormatError(f"temp_{probe} has no finite value to bin on")
    idx = np.floor((tt - tt.min()) / bin_c).astype(np.int64)
    nb = int(idx.max()) + 1
    cnt = np.bincount(idx, minlength=nb)
    good = cnt >= max(1, min_count)
    cols = {}
    for name, col in ds.columns.items():
        if name == "orientation":
            continue
        v = np.asarray(col, dtype=np.float64)[ok]
        f = np.isfinite(v)
        n = np.bincount(idx, f.astype(np.float64), nb)
        s = np.bincount(idx, np.where(f, v, 0.0), nb)
        with np.errstate(invalid="ignore", divide="ignore"):
            cols[name] = np.where(n > 0, s / np.maximum(n, 1), np.nan)[good]
    order = np.argsort(cols["time_s"])
    cols = {k: v[order] for k, v in cols.items()}
    cols["bin_count"] = cnt[good][order].astype(np.float64)
    meta = dict(ds.meta)
    meta["binned_on"] = f"temp_{probe}"
    meta["bin_c"] = repr(float(bin_c))
    return Dataset(cols, meta)


# -------------------------------------------------------------------------------------------- rates
def rate_c_per_min(time_s: np.ndarray, temp_c: np.ndarray, window_s: float = DEFAULT_RATE_WINDOW_S) -> np.ndarray:
    """dT/dt in C/min: ``bench.signal.temperature_rate`` with the ``"centred_slope"`` method."""
    return temperature_rate(time_s, temp_c, window_s, method="centred_slope")


def add_rates(ds: Dataset, window_s: float = DEFAULT_RATE_WINDOW_S, names: list[str] | None = None) -> Dataset:
    """Add ``rate_<name>`` (C/min) for each ``temp_<name>`` (or only ``names``)."""
    names = ds.temp_names() if names is None else names
    cols = {f"rate_{n}": rate_c_per_min(ds.time, ds[f"temp_{n}"], window_s) for n in names}
    out = ds.with_columns(**cols)
    out.meta["rate_window_s"] = repr(float(window_s))
    return out


def gradient(ds: Dataset, a: str, b: str) -> np.ndarray:
    """Temperature difference temp_a - temp_b (C), the gradient term of S000 eq 4."""
    return np.asarray(ds[f"temp_{a}"], dtype=np.float64) - np.asarray(ds[f"temp_{b}"], dtype=np.float64)


# --------------------------------------------------------------------------------------- Earth rate
def _latitude(ds: Dataset, latitude_deg: float | None) -> float:
    if latitude_deg is not None:
        return float(latitude_deg)
    if "latitude_deg" in ds.meta:
        return float(ds.meta["latitude_deg"])
    raise DataFormatError("latitude unknown: pass latitude_deg or put '# latitude_deg: ...' in the data")


def _orientation_codes(ds: Dataset) -> np.ndarray:
    if "orientation" not in ds:
        return np.full(len(ds), ORIENTATION_DEFAULT, dtype=object)
    o = np.asarray(ds["orientation"], dtype=object)
    return np.where(o == "", ORIENTATION_DEFAULT, o)


def body_earth_rates(ds: Dataset, latitude_deg: float | None = None) -> np.ndarray:
    """(n, 3) Earth rate on body x, y, z per sample (deg/h) from orientation and latitude."""
    return earth_rate_body_per_sample(_orientation_codes(ds), _latitude(ds, latitude_deg), ORIENTATION_DEFAULT)


def default_axis(channel: str) -> np.ndarray:
    """Sensing axis of channel ``x``/``y``/``z`` in the body frame; other names need an explicit axis."""
    if channel not in _BODY:
        raise DataFormatError(f"sensing axis of channel {channel!r} unknown: pass axis= (a body-frame vector, "
                              "e.g. a row of channel_axes_from_m(M))")
    v = np.zeros(3)
    v[_BODY[channel]] = 1.0
    return v


def earth_rate_reading(ds: Dataset, channel: str, latitude_deg: float | None = None,
                       axis: np.ndarray | None = None) -> np.ndarray:
    """Earth rate seen by ``gyro_<channel>`` per sample (deg/h)."""
    a = default_axis(channel) if axis is None else np.asarray(axis, dtype=np.float64)
    return body_earth_rates(ds, latitude_deg) @ a


def remove_earth_rate(ds: Dataset, latitude_deg: float | None = None,
                      axes: dict[str, np.ndarray] | None = None) -> Dataset:
    """Return ``ds`` with the Earth rate subtracted from every ``gyro_<ch>`` (axes: channel -> body
    vector; channels x/y/z default to the body axes).  Sets ``meta['earth_rate_removed'] = 'yes'``."""
    if ds.meta.get("earth_rate_removed") == "yes":
        raise DataFormatError("Earth rate already removed from this dataset")
    omega = body_earth_rates(ds, latitude_deg)
    axes = axes or {}
    cols = {}
    for ch in ds.gyro_channels():
        a = axes.get(ch)
        a = default_axis(ch) if a is None else np.asarray(a, dtype=np.float64)
        cols[f"gyro_{ch}"] = np.asarray(ds[f"gyro_{ch}"], dtype=np.float64) - omega @ a
    out = ds.with_columns(**cols)
    out.meta["earth_rate_removed"] = "yes"
    return out


# ------------------------------------------------------------------------------- installation matrix
def channel_axes_from_m(m: np.ndarray) -> np.ndarray:
    """Rows = channel sensing axes (with scale) in the system frame: inv(M) of S000 eq 1."""
    return np.linalg.inv(np.asarray(m, dtype=np.float64))


def to_system_axes(ds: Dataset, m: np.ndarray, channels=("1", "2", "3"), out=("x", "y", "z")) -> Dataset:
    """S000 eq 1: [w_x, w_y, w_z] = M @ [w_1, w_2, w_3]; adds gyro_<out> columns."""
    w = np.vstack([np.asarray(ds[f"gyro_{c}"], dtype=np.float64) for c in channels])
    s = np.asarray(m, dtype=np.float64) @ w
    return ds.with_columns(**{f"gyro_{o}": s[i] for i, o in enumerate(out)})


def to_channel_axes(ds: Dataset, m: np.ndarray, system=("x", "y", "z"), channels=("1", "2", "3")) -> Dataset:
    """Inverse of ``to_system_axes``: [w_1, w_2, w_3] = inv(M) @ [w_x, w_y, w_z]."""
    return to_system_axes(ds, np.linalg.inv(np.asarray(m, dtype=np.float64)), system, channels)


@dataclass
class EightPositionResult:
    """Result of the eight-position test (S000 3.2).

    ``bias``: channel -> bias (deg/h, Earth rate separated); ``m``: installation matrix (S000 eq 1,
    system = M @ channel, unit scale assumed 1 deg/h per deg/h); ``a`` = inv(M) (rows = channel axes);
    ``position_means``: code -> per-channel mean; ``residual_rms_dph`` of the per-position fit."""

    channels: list[str]
    bias: dict[str, float]
    m: np.ndarray
    a: np.ndarray
    position_means: dict[str, list[float]]
    residual_rms_dph: float
    latitude_deg: float
    extra: dict = field(default_factory=dict)


def eight_position(ds: Dataset, channels: list[str] | tuple[str, ...] | None = None,
                   latitude_deg: float | None = None, settle_s: float = 0.0) -> EightPositionResult:
    """Separate bias and Earth rate, and estimate M, from multi-position static data.

    Per position (consecutive samples with the same orientation code; the first ``settle_s`` seconds of
    each dwell are skipped), the channel means y_k are modelled as y_k = b + A @ Omega_body(k) and solved
    by least squares over all positions (at least 4 with independent Earth-rate projections; the
    eight S000 positions give a well-posed problem).  M = inv(A)."""
    if "orientation" not in ds:
        raise DataFormatError("eight-position data needs an orientation column")
    lat = _latitude(ds, latitude_deg)
    channels = list(channels or ds.gyro_channels())
    if len(channels) != 3:
        raise DataFormatError(f"eight-position needs exactly 3 gyro channels, got {channels}")
    codes = np.asarray(ds["orientation"], dtype=object)
    t = ds.time
    start = np.r_[0, np.flatnonzero(codes[1:] != codes[:-1]) + 1]
    stop = np.r_[start[1:], len(codes)]
    rows_w, rows_y, means = [], [], {}
    for s, e in zip(start, stop):
        code = codes[s]
        if code == "":
            continue
        sel = slice(s, e)
        use = t[sel] >= t[s] + settle_s
        y = np.array([np.nanmean(np.asarray(ds[f"gyro_{c}"], dtype=np.float64)[sel][use]) for c in channels])
        if not np.all(np.isfinite(y)):
            continue
        rows_w.append(earth_rate_body(code, lat))
        rows_y.append(y)
        means.setdefault(code, []).append(y.tolist())
    if len(rows_w) < 4:
        raise DataFormatError(f"eight-position: need at least 4 positions, found {len(rows_w)}")
    g = np.hstack([np.ones((len(rows_w), 1)), np.array(rows_w)])
    if np.linalg.matrix_rank(g) < 4:
        raise DataFormatError("eight-position: positions do not separate bias from Earth rate (rank < 4)")
    sol, *_ = np.linalg.lstsq(g, np.array(rows_y), rcond=None)
    bias, a = sol[0], sol[1:].T
    resid = np.array(rows_y) - g @ sol
    return EightPositionResult(
        channels=channels, bias={c: float(bias[i]) for i, c in enumerate(channels)}, m=np.linalg.inv(a), a=a,
        position_means={k: np.mean(v, axis=0).tolist() for k, v in means.items()},
        residual_rms_dph=float(np.sqrt(np.mean(resid ** 2))), latitude_deg=lat)
