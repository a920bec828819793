"""Generic, vectorised particle-swarm optimiser (global-best topology).

Source: seed 002 (DONG et al., HRG temperature compensation with PSO), section 3.2, steps 1-5:
swarm of N = 200 particles, 200 iterations, learning factors c1 = c2 = 1.5, inertia w = 0.8,
uniform initialisation inside the search box, velocity limited to the same span as the position box
(the paper uses position and velocity both in [-1, 1]), velocity update eq (9)
``V <- w V + c1 r1 (P_i - X) + c2 r2 (P_g - X)`` and position update eq (10) ``X <- X + V``.

Choices made here (the paper leaves them open):
* r1, r2 are drawn per particle *and* per dimension from a seedable ``numpy.random.Generator``;
* positions leaving the box are clipped to the bound and that velocity component is zeroed;
* optional seed particles (e.g. the least-squares solution, calibration-notes lesson 10) replace the
  first particles of the initial swarm, clipped into the box.

The cost function is evaluated for the whole swarm at once: ``cost(X)`` with ``X`` of shape
(n_particles, n_dims) must return an array of shape (n_particles,).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from bench.errors import DataFormatError

CostFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PsoSettings:
    """Swarm settings; defaults are the paper's (seed 002, step 1)."""

    n_particles: int = 200
    iterations: int = 200
    c1: float = 1.5
    c2: float = 1.5
    w: float = 0.8
    velocity_fraction: float = 0.5   # vmax = fraction * (upper - lower); paper: [-1,1] on a [-1,1] box
    seed: int | None = 0

    def check(self) -> None:
        if self.n_particles < 2:
            raise DataFormatError(f"PSO n_particles must be >= 2, got {self.n_particles}", source="PSO")
        if self.iterations < 1:
            raise DataFormatError(f"PSO iterations must be >= 1, got {self.iterations}", source="PSO")
        if not (0.0 <= self.w < 1.0):
            raise DataFormatError(f"PSO inertia w must be in [0, 1), got {self.w}", source="PSO")
        if self.c1 < 0 or self.c2 < 0:
            raise DataFormatError(f"PSO learning factors must be >= 0, got c1={self.c1}, c2={self.c2}", source="PSO")
        if not (0.0 < self.velocity_fraction <= 1.0):
            raise DataFormatError(f"PSO velocity_fraction must be in (0, 1], got {self.velocity_fraction}", source="PSO")


@dataclass
class PsoResult:
    best_position: np.ndarray
    best_cost: float
    history: np.ndarray                 # global-best cost after initialisation and each iteration
    n_evaluations: int
    seeded: bool
    at_bound: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # dims pinned to the box


def minimize(cost: CostFn, lower: np.ndarray, upper: np.ndarray, *,
             settings: PsoSettings = PsoSettings(),
             initial: np.ndarray | None = None) -> PsoResult:
    """Minimise ``cost`` over the box [lower, upper] with a global-best PSO.

    ``initial``: optional seed positions, shape (k, n_dims) or (n_dims,), k <= n_particles.
    """
    settings.check()
    lower = np.asarray(lower, float).ravel()
    upper = np.asarray(upper, float).ravel()
    if lower.shape != upper.shape or lower.size == 0:
        raise DataFormatError(f"PSO bounds must be two equal-length 1-D arrays, got {lower.shape} and {upper.shape}", source="PSO")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(upper > lower)):
        raise DataFormatError("PSO bounds must be finite with upper > lower in every dimension", source="PSO")
    n, d = settings.n_particles, lower.size
    rng = np.random.default_rng(settings.seed)
    span = upper - lower
    vmax = settings.velocity_fraction * span

    x = lower + rng.random((n, d)) * span
    v = (rng.random((n, d)) * 2.0 - 1.0) * vmax
    seeded = False
    if initial is not None:
        seeds = np.atleast_2d(np.asarray(initial, float))
        if seeds.shape[1] != d or seeds.shape[0] > n:
            raise DataFormatError(f"PSO seed particles must have shape (k<={n}, {d}), got {seeds.shape}", source="PSO")
        x[: seeds.shape[0]] = np.clip(seeds, lower, upper)
        seeded = True

    def evaluate(pos: np.ndarray) -> np.ndarray:
        values = np.asarray(cost(pos), float).reshape(-1)
        if values.shape != (n,):
            raise DataFormatError(f"PSO cost must return shape ({n},), got {values.shape}", source="PSO")
        return np.where(np.isfinite(values), values, np.inf)

    fx = evaluate(x)
    p_best, p_cost = x.copy(), fx.copy()
    g = int(np.argmin(p_cost))
    g_best, g_cost = p_best[g].copy(), float(p_cost[g])
    history = np.empty(settings.iterations + 1)
    history[0] = g_cost
    for it in range(settings.iterations):
        r1 = rng.random((n, d))
        r2 = rng.random((n, d))
        v = settings.w * v + settings.c1 * r1 * (p_best - x) + settings.c2 * r2 * (g_best - x)
        np.clip(v, -vmax, vmax, out=v)
        x = x + v
        outside = (x < lower) | (x > upper)
        if outside.any():
            np.clip(x, lower, upper, out=x)
            v[outside] = 0.0
        fx = evaluate(x)
        better = fx < p_cost
        p_best[better] = x[better]
        p_cost[better] = fx[better]
        g = int(np.argmin(p_cost))
        if p_cost[g] < g_cost:
            g_best, g_cost = p_best[g].copy(), float(p_cost[g])
        history[it + 1] = g_cost
    tol = 1e-9 * span
    at_bound = (np.abs(g_best - lower) <= tol) | (np.abs(g_best - upper) <= tol)
    return PsoResult(best_position=g_best, best_cost=g_cost, history=history,
                     n_evaluations=n * (settings.iterations + 1), seeded=seeded, at_bound=at_bound)
