"""Gyro noise processes, deterministic with a seed and independent of how time is chunked.

IEEE Std 952 Allan-variance terms (calibration-notes section 2.2):

* angle random walk N (deg/sqrt(h)): white rate noise; for samples averaged over ``period_s`` the
  standard deviation is ``60 * N / sqrt(period_s)`` deg/h, so ADEV(tau) = 60 N / sqrt(tau [s]).
* bias instability: a sum of first-order Gauss-Markov processes (sigma, tau); exact AR(1)
  discretisation x_k = phi x_{k-1} + sigma sqrt(1 - phi^2) e_k, phi = exp(-h / tau).
* rate random walk K (deg/h/sqrt(h)): r_k = r_{k-1} + K sqrt(h / 3600 s) e_k.

Each process draws from its own ``numpy.random.Generator`` seeded by ``[seed, stream, channel]`` so
results do not depend on the order in which streams are used nor on the chunk sizes of the calls
(numpy generators give the same sequence whether drawn in one call or several).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter   # at import: importing it mid-run would stall the simulators

from bench.sim.scenario import ChannelNoise, RandomSteps

# stream identifiers (part of the seed; never renumber, or recorded runs change)
STREAM_WHITE = 1
STREAM_GAUSS_MARKOV = 2
STREAM_RRW = 3
STREAM_ACCEL = 4
STREAM_FREQ = 5
STREAM_STEPS = 6


def stream_rng(seed: int, stream: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, stream, index])


SHORT_RUN = 32      # below this many steps a Python recursion beats one lfilter call per column


def first_order_recursion(phi, x: np.ndarray, y0) -> np.ndarray:
    """y[k] = phi * y[k-1] + x[k] with y[-1] = y0, down axis 0 of ``x`` ((n,) with scalar phi / y0, or
    (n, m) with phi / y0 of shape (m,)).  The same arithmetic as ``lfilter([1], [1, -phi], x, zi=[phi y0])``
    (identical values); short runs (one lockstep instant: a step or two) skip lfilter's per-call cost."""
    n = x.shape[0]
    if n < SHORT_RUN:
        out = np.empty_like(x)
        prev = y0
        for k in range(n):
            prev = phi * prev + x[k]
            out[k] = prev
        return out
    if x.ndim == 1:
        return lfilter([1.0], [1.0, -phi], x, zi=[phi * y0])[0]
    out = np.empty_like(x)
    for j in range(x.shape[1]):
        out[:, j], _ = lfilter([1.0], [1.0, -phi[j]], x[:, j], zi=[phi[j] * y0[j]])
    return out


class CorrelatedNoise:
    """Gauss-Markov sum + rate random walk for one channel, advanced on the physics grid (deg/h)."""

    def __init__(self, spec: ChannelNoise, seed: int, channel_index: int) -> None:
        self._spec = spec
        self._rng_gm = stream_rng(seed, STREAM_GAUSS_MARKOV, channel_index)
        self._rng_rrw = stream_rng(seed, STREAM_RRW, channel_index)
        k = len(spec.gauss_markov)
        # stationary start for the Gauss-Markov states, rate random walk starts at 0
        sig = np.array([gm.sigma_dph for gm in spec.gauss_markov])
        self._gm = sig * self._rng_gm.standard_normal(k) if k else np.zeros(0)
        self._rrw = 0.0

    @property
    def value(self) -> float:
        return float(self._gm.sum() + self._rrw)

    def get_state(self) -> tuple:
        return (self._rng_gm.bit_generator.state, self._rng_rrw.bit_generator.state, self._gm.copy(), self._rrw)

    def set_state(self, state: tuple) -> None:
        gm_rng, rrw_rng, gm, self._rrw = state
        self._rng_gm.bit_generator.state = gm_rng
        self._rng_rrw.bit_generator.state = rrw_rng
        self._gm = gm.copy()

    def advance(self, n: int, h: float) -> np.ndarray:
        """Advance ``n`` grid steps of ``h`` seconds; return the values after each step, shape (n,)."""
        out = np.zeros(n)
        if n <= 0:
            return out
        gms = self._spec.gauss_markov
        if gms:
            e = self._rng_gm.standard_normal((n, len(gms)))
            for j, gm in enumerate(gms):
                phi = np.exp(-h / gm.tau_s)
                drive = gm.sigma_dph * np.sqrt(1.0 - phi * phi) * e[:, j]
                y = first_order_recursion(float(phi), drive, float(self._gm[j]))
                self._gm[j] = y[-1]
                out += y
        if self._spec.rrw_dph_rt_h > 0:
            steps = self._spec.rrw_dph_rt_h * np.sqrt(h / 3600.0) * self._rng_rrw.standard_normal(n)
            walk = self._rrw + np.cumsum(steps)
            self._rrw = float(walk[-1])
            out += walk
        return out


class WhiteNoise:
    """White rate noise for one channel; one draw per output sample."""

    def __init__(self, spec: ChannelNoise, seed: int, channel_index: int) -> None:
        self._arw = spec.arw_deg_rt_h
        self._rng = stream_rng(seed, STREAM_WHITE, channel_index)

    def get_state(self) -> dict:
        return self._rng.bit_generator.state

    def set_state(self, state: dict) -> None:
        self._rng.bit_generator.state = state

    def draw(self, n: int, period_s: float) -> np.ndarray:
        if self._arw <= 0:
            return np.zeros(n)
        return (60.0 * self._arw / np.sqrt(period_s)) * self._rng.standard_normal(n)


class RandomStepLevels:
    """Piecewise-constant bias steps at Poisson arrival times (the 'unexplained' disturbance).

    Arrivals are generated lazily in time order from their own stream, so the level at a given
    time never depends on how the caller chunked time.
    """

    def __init__(self, spec: RandomSteps, seed: int, start_s: float, n_channels: int) -> None:
        self._rng = stream_rng(seed, STREAM_STEPS)
        self._mean_gap_s = 3600.0 / spec.rate_per_h
        self._sigma = spec.sigma_dph
        self._n = n_channels
        self._times: list[float] = []
        self._amps: list[np.ndarray] = []
        self._last = float(start_s)

    def _extend_to(self, t: float) -> None:
        while self._last <= t:
            self._last += float(self._rng.exponential(self._mean_gap_s))
            self._times.append(self._last)
            self._amps.append(self._sigma * self._rng.standard_normal(self._n))

    def levels(self, times: np.ndarray) -> np.ndarray:
        """Cumulative step level at each time, shape (len(times), n_channels), deg/h."""
        times = np.asarray(times, dtype=float)
        if times.size == 0:
            return np.zeros((0, self._n))
        self._extend_to(float(times.max()))
        arrivals = np.array(self._times)
        cum = np.vstack([np.zeros(self._n), np.cumsum(np.array(self._amps), axis=0)])
        idx = np.searchsorted(arrivals, times, side="right")
        return cum[idx]

    def step_times(self) -> list[float]:
        return list(self._times)
