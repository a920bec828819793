"""Physics of the fifth referee: chamber, thermal network, probes, gyro noise, memory operators.

Written from first principles, independently of the product's analysis code.

Conventions (all arrays are sampled on a uniform 1-s simulation grid unless said otherwise):

* Time is in seconds from the start of the *simulation* (``sim_t``), which begins before the
  recording: a run's recording starts ``t_rec0`` seconds later, part-way through a soak or even a
  ramp, so that every lag or memory state at the first recorded row is the result of an earlier
  temperature history (not an equilibrium the analysis could assume).
* Chamber: the programme is a piecewise-linear set point (``knots``: (time_s, degC)).  The air
  follows it through a first-order controller lag (60-150 s) plus a slow, small stirring wobble
  (an Ornstein-Uhlenbeck process, ~0.05 C, 200 s).  ``chamber_pv`` is the air read by the chamber's
  own sensor (0.1 C resolution); ``chamber_sp`` the set point.
* Thermal network (lumped, linear): nodes ``case``, ``plate`` (mounting plate), ``board``
  (electronics, self-heated by 0.6-1.6 W while powered) and one sensing element per axis
  ``elem_x``, ``elem_y``, ``elem_z``.  C_i dT_i/dt = sum_j G_ij (T_j - T_i) + G_i,air (T_air - T_i)
  + Q_i * power.  Capacities and conductances are drawn so that the node time constants fall in
  ~200-3000 s.  The network is discretised exactly (zero-order hold on air and power, matrix
  exponential) and started in equilibrium with the first air temperature and power state.
* Probes (DS18B20): a probe is glued on a node; it reads the node through its own first-order glue
  lag (10-90 s), adds an offset (+-0.3 C) and a little conversion noise, is quantised to 0.0625 C,
  refreshed every ``probe_period_s`` (1 or 2 s; held in between) and sometimes fails (NaN = empty
  cell in the CSV).
* Gyro noise (deg/h): angle random walk (white, ARW N deg/sqrt(h) -> density 60 N deg/h/sqrt(Hz)),
  bias instability (1/f flicker, PSD B^2/(2 pi f) one-sided... see ``flicker``) and rate random walk
  (K deg/h/sqrt(h)).
* Rates are in degC/min throughout.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, lfilter_zi

NODES = ("case", "plate", "board", "elem_x", "elem_y", "elem_z")


# ----------------------------------------------------------------------------------------------
# chamber
# ----------------------------------------------------------------------------------------------

def setpoint(knots, n: int, dt: float = 1.0) -> np.ndarray:
    """Piecewise-linear set point through ``knots`` [(t_s, degC), ...] on an n-sample grid."""
    kt = np.array([k[0] for k in knots], float)
    kv = np.array([k[1] for k in knots], float)
    return np.interp(np.arange(n) * dt, kt, kv)


def ou_process(rng, n: int, tau: float, sigma: float, dt: float = 1.0) -> np.ndarray:
    """Stationary Ornstein-Uhlenbeck process (std ``sigma``, correlation time ``tau``)."""
    a = np.exp(-dt / tau)
    e = rng.standard_normal(n) * sigma * np.sqrt(1 - a * a)
    zi = np.array([a * rng.standard_normal() * sigma])
    return lfilter([1.0], [1.0, -a], e, zi=zi)[0]


def chamber_air(rng, sp: np.ndarray, dt: float = 1.0):
    """Air temperature following the set point; returns (air, pv)."""
    tau = rng.uniform(60, 150)
    air = first_order_lag(sp, tau, dt) + ou_process(rng, len(sp), 200.0, rng.uniform(0.02, 0.06), dt)
    pv = np.round((air + 0.03 * rng.standard_normal(len(sp))) / 0.1) * 0.1
    return air, pv


# ----------------------------------------------------------------------------------------------
# thermal network
# ----------------------------------------------------------------------------------------------

@dataclass
class ThermalNetwork:
    cap: np.ndarray            # J/K per node
    g_air: np.ndarray          # W/K node -> air
    g: np.ndarray              # W/K symmetric node-node conductance matrix (zero diagonal)
    q_power: np.ndarray        # W per node while powered

    @classmethod
    def draw(cls, rng) -> "ThermalNetwork":
        n = len(NODES)
        u = rng.uniform
        cap = np.array([u(500, 900), u(900, 1600), u(80, 160), u(60, 140), u(60, 140), u(60, 140)])
        g_air = np.array([u(0.45, 0.9), u(0.5, 1.0), u(0.01, 0.04), 0.0, 0.0, 0.0])
        g = np.zeros((n, n))

        def link(a, b, val):
            i, j = NODES.index(a), NODES.index(b)
            g[i, j] = g[j, i] = val

        link("case", "plate", u(0.3, 0.9))
        link("case", "board", u(0.08, 0.2))
        # each element has its own path: x mostly through the plate, y the case, z the case + board
        link("elem_x", "plate", u(0.08, 0.25))
        link("elem_x", "case", u(0.02, 0.05))
        link("elem_y", "case", u(0.05, 0.2))
        link("elem_z", "case", u(0.03, 0.1))
        link("elem_z", "board", u(0.03, 0.08))
        link("elem_y", "board", u(0.005, 0.02))
        q = np.array([0.0, 0.0, u(0.6, 1.6), 0.0, 0.0, 0.0])
        return cls(cap, g_air, g, q)

    def _continuous(self):
        n = len(NODES)
        a = self.g.copy()
        a[np.diag_indices(n)] = -(self.g.sum(axis=1) + self.g_air)
        a /= self.cap[:, None]
        b = np.column_stack([self.g_air / self.cap, self.q_power / self.cap])
        return a, b

    def time_constants(self) -> np.ndarray:
        a, _ = self._continuous()
        return np.sort(-1.0 / np.linalg.eigvals(a).real)

    def simulate(self, air: np.ndarray, power: np.ndarray, dt: float = 1.0) -> np.ndarray:
        """Node temperatures, shape (len(air), n_nodes); equilibrium start."""
        a, b = self._continuous()
        n = a.shape[0]
        m = np.zeros((n + 2, n + 2))
        m[:n, :n] = a
        m[:n, n:] = b
        e = expm(m * dt)
        ad, bd = e[:n, :n], e[:n, n:]
        u = np.column_stack([air, power.astype(float)])
        x = np.linalg.solve(-a, b @ u[0])
        out = np.empty((len(air), n))
        # the loop is cheap: 6x6 per step
        for k in range(len(air)):
            out[k] = x
            x = ad @ x + bd @ u[k]
        return out


# ----------------------------------------------------------------------------------------------
# probes
# ----------------------------------------------------------------------------------------------

@dataclass
class Probe:
    name: str
    node: str
    glue_tau: float
    offset: float
    noise: float = 0.01
    fail_prob: float = 0.002

    def at_probe(self, node_temp: np.ndarray, dt: float = 1.0) -> np.ndarray:
        """True (noise-free, offset-free) temperature at the probe: the node through the glue lag."""
        return first_order_lag(node_temp, self.glue_tau, dt)

    def read(self, rng, at_probe: np.ndarray, period_s: int = 1) -> np.ndarray:
        """DS18B20 readings on the 1-s grid (held between conversions; NaN = failed reading)."""
        y = at_probe + self.offset + self.noise * rng.standard_normal(len(at_probe))
        y = np.round(y / 0.0625) * 0.0625
        if period_s > 1:
            idx = (np.arange(len(y)) // period_s) * period_s
            y = y[idx]
        fail = rng.random(len(y)) < self.fail_prob
        y = y.copy()
        y[fail] = np.nan
        return y


# ----------------------------------------------------------------------------------------------
# gyro noise
# ----------------------------------------------------------------------------------------------

def flicker(rng, n: int, b_inst: float, dt: float = 1.0) -> np.ndarray:
    """1/f rate noise with bias instability ``b_inst`` (deg/h): one-sided PSD S(f) = B^2 / (pi f),
    so that the Allan deviation plateau is 0.664 B (IEEE 952; checked numerically).  Generated by
    FFT on a record twice as long (the circular wrap is discarded)."""
    m = 2 * n
    f = np.fft.rfftfreq(m, dt)
    s = np.zeros_like(f)
    s[1:] = b_inst ** 2 / (2 * np.pi * f[1:]) * 2.0   # one-sided
    c = np.sqrt(s * m / (4 * dt))
    x = c * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f)))
    x[0] = 0.0
    y = np.fft.irfft(x, n=m)
    return y[:n]


@dataclass
class GyroNoise:
    arw: float      # deg/sqrt(h)
    b_inst: float   # deg/h
    rrw: float      # deg/h/sqrt(h)

    def generate(self, rng, n: int, dt: float = 1.0) -> np.ndarray:
        white = 60.0 * self.arw / np.sqrt(dt) * rng.standard_normal(n)
        fl = flicker(rng, n, self.b_inst, dt)
        rw = np.cumsum(rng.standard_normal(n)) * self.rrw * np.sqrt(dt / 3600.0)
        return white + fl + rw - rw.mean()


# ----------------------------------------------------------------------------------------------
# signal operators (used by the truth on the 1-s grid and by the oracle on recorded rows)
# ----------------------------------------------------------------------------------------------

def first_order_lag(x: np.ndarray, tau: float, dt: float = 1.0, x0: float | None = None) -> np.ndarray:
    """y' = (x - y)/tau on a uniform grid, started at rest at x0 (default x[0])."""
    a = np.exp(-dt / tau)
    b, den = [1 - a], [1.0, -a]
    zi = lfilter_zi(b, den) * (x[0] if x0 is None else x0)
    return lfilter(b, den, x, zi=zi)[0]


def lag_on_times(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    """First-order lag on a possibly non-uniform time grid (exact for a held input)."""
    y = np.empty_like(x)
    y[0] = x[0]
    a = np.exp(-np.diff(t) / tau)
    for k in range(1, len(x)):
        y[k] = a[k - 1] * y[k - 1] + (1 - a[k - 1]) * x[k]
    return y


def local_slope(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Centred least-squares slope of x over |t' - t| <= window/2, in units of x per minute."""
    tt = (t - t[0]) / 1000.0
    lo = np.searchsorted(t, t - window_s / 2, side="left")
    hi = np.searchsorted(t, t + window_s / 2, side="right")

    def c(v):
        return np.concatenate([[0.0], np.cumsum(v)])

    s1, st, sx, stt, stx = c(np.ones_like(tt)), c(tt), c(x), c(tt * tt), c(tt * x)
    n = s1[hi] - s1[lo]
    a_t, a_x = st[hi] - st[lo], sx[hi] - sx[lo]
    a_tt, a_tx = stt[hi] - stt[lo], stx[hi] - stx[lo]
    den = n * a_tt - a_t ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(den > 0, (n * a_tx - a_t * a_x) / den, 0.0)
    return slope / 1000.0 * 60.0


def relay_on_rate(rate: np.ndarray, threshold: float, s0: float = 0.0) -> np.ndarray:
    """Heating/cooling relay: +1 after the rate last exceeded +threshold, -1 after it last fell
    below -threshold; holds during soaks; ``s0`` before the first crossing."""
    s = np.full(len(rate), np.nan)
    s[rate > threshold] = 1.0
    s[rate < -threshold] = -1.0
    idx = np.where(np.isnan(s), 0, np.arange(len(s)))
    np.maximum.accumulate(idx, out=idx)
    out = s[idx]
    out[np.isnan(out)] = s0
    return out


def play_operator(x: np.ndarray, width: float, y0: float | None = None) -> np.ndarray:
    """Backlash (play) operator of total width ``width``: output follows x with a dead band.
    Returns x - y, which lies in [-width/2, +width/2] (sign: + after heating)."""
    h = width / 2.0
    y = np.empty_like(x)
    yk = x[0] if y0 is None else y0
    for k, xk in enumerate(x):
        if xk - yk > h:
            yk = xk - h
        elif yk - xk > h:
            yk = xk + h
        y[k] = yk
    return x - y


def duhem_memory(x: np.ndarray, width: float, z0: float = 0.0) -> np.ndarray:
    """Saturating Duhem memory: dz = |dx|/width * (sign(dx) - z); z in [-1, 1], it forgets the
    previous direction over a temperature travel of ~``width``."""
    dx = np.diff(x, prepend=x[0])
    decay = np.exp(-np.abs(dx) / width)
    sgn = np.sign(dx)
    z = np.empty_like(x)
    zk = z0
    for k in range(len(x)):
        if sgn[k] != 0:
            zk = sgn[k] + (zk - sgn[k]) * decay[k]
        z[k] = zk
    return z


def block_means(t: np.ndarray, y: np.ndarray, t0: float, block_s: float = 100.0,
                min_fill: float = 0.5, period_s: float = 1.0):
    """Means of y over 100-s blocks counted from t0 (NaN samples enter no mean).  Returns
    (block index array, means, counts) for blocks with at least ``min_fill`` of their samples."""
    b = np.floor((t - t0) / block_s).astype(int)
    ok = np.isfinite(y)
    nb = b.max() + 1
    cnt = np.bincount(b[ok], minlength=nb)
    s = np.bincount(b[ok], weights=y[ok], minlength=nb)
    keep = cnt >= min_fill * block_s / period_s
    idx = np.nonzero(keep)[0]
    return idx, s[idx] / cnt[idx], cnt[idx]


def std100(t, y, t0, period_s=1.0) -> float:
    _, m, _ = block_means(t, y, t0, period_s=period_s)
    return float(np.std(m, ddof=1)) if len(m) > 1 else float("nan")


@dataclass
class Hardware:
    """One gyro on its fixture: network, probes and noise parameters."""
    net: ThermalNetwork
    probes: list
    channel_probes: dict
    noise: dict = field(default_factory=dict)   # ch -> GyroNoise
