"""Close the loop, step 2: choose the effects the declared model lacks, on the TRAINING run only.

The search runs on block means: every effect column is built on a fine grid (10-s means of the
inputs; the regressors are smooth) and averaged into 100-s evidence blocks, where the model is
linear, the white noise is mostly gone and one point is about one thermal time step.

Evidence that survives autocorrelation, all on TRAIN:

* delta-BIC with the effective number of points n_eff = n (1 - rho) / (1 + rho) (rho: lag-1
  autocorrelation of the 100-s residual of the larger model); the penalty counts every column and
  every searched parameter: ln(n_eff) for a continuous one (time constant, width, threshold, filter
  window), ln(number of options) for the probe or pair chosen (none for the declared model's own
  probe);
* a Wald test of the new coefficients with Newey-West (HAC) covariance;
* blocked cross-validation: the training run is cut into contiguous segments; each is predicted by
  the model fitted on the others, on the blocks where the declared inputs lie inside the range the
  other segments cover (no extrapolation is scored).

Step: for every family (kind x probe/pair/form) the continuous parameter is scanned on its grid and
refined (bounded golden section on log scale) by the training sum of squares; families that pass
the three gates (delta-BIC > 10, HAC p < 1e-3, cross-validated error lower by >= 2 %) are ranked by
delta-BIC (which charges every column and every searched parameter) and the best is added.  Then the nonlinear parameters of ALL added effects are
re-fitted jointly (coordinate sweeps; probe, pair and form re-chosen within each kind).  When no
single addition passes or when a pair does clearly better than the best single (BIC), pairs of the
strongest families are added together.  Stop when nothing passes or after ``MAX_EFFECTS``.  Then an
exchange pass (``exchange``): a chosen effect (or two, merged) is replaced by the family that best
fills its place when that lowers the BIC; then the backward pass (``prune``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import minimize_scalar

from bench.fit import effects as fx
from bench.signal import BlockPlan, block_means, hac_wald_test, lag1_autocorrelation, newey_west_lags

FINE_S = 10.0
BLOCK_S = 100.0
P_MAX = 1e-3
DBIC_MIN = 10.0
MIN_CV_GAIN = 0.02
MAX_EFFECTS = 4
# a memory's delay is profiled with its width re-fitted within this factor (log) of its current width
DELAY_PROFILE_SPAN = float(np.log(2.0))
CV_FOLDS = 8
PAIR_POOL = 8
PAIR_DBIC = 6.0
SCORED_SINGLES = 12
SSR_MEMO = 200_000            # training SSRs kept per search problem (by the effects' labels)
JOINT_SWEEPS = 2
EXCHANGE_CANDIDATES = 4       # families tried in an exchanged effect's place, by training SSR
LOOKALIKE_CANDIDATES = 12     # families tried in a chosen effect's place when naming its look-alikes
EXCHANGE_ROUNDS = 4
SPAN_RTOL = 1e-6              # columns within a span to rounding (``SearchProblem.lies_within``)
# two candidates whose training BIC differ by less than this are named as an ambiguity (Kass & Raftery:
# below 6 the evidence for one over the other is at most "positive", never "strong")
AMBIGUOUS_DBIC = 6.0
# below this the training BIC cannot break a tie ("not worth more than a bare mention")
TIE_DBIC = 2.0
# the verdict's tolerance: a std of 100-s means within this factor of the noise floor is at the floor.
# The search's stop floor this much above the floor once the best passing addition is in had read
# structure as noise
AT_FLOOR_RATIO = 1.2


def replacement_margin(new: fx.Family, replaced: tuple[fx.Family, ...], restriction: bool = False) -> float:
    """The training BIC a family must gain to take the place of the ``replaced`` families: another value
    of the same family, any gain; beyond a tie (``TIE_DBIC``) for another form, probe or kind; strong
    evidence (``DBIC_MIN``) for a richer form of one of them (``fx.Family.nests``) or one family in place
    of two (a merge takes out an effect the forward selection added on strong evidence).  When a third
    family's columns lie within the span of the two it replaces (``restriction``: gradients t1-t3 and
    t2-t3 hold t1-t2), the two are a richer form of it and keep their place only on strong evidence
    (the margin is -``DBIC_MIN``); one of the two re-fitted in place of both is a backward step, the
    backward pass's to judge (``prune``)."""
    if replaced == (new,):
        return 0.0
    if restriction and len(replaced) > 1 and new not in replaced:
        return -DBIC_MIN
    if len(replaced) > 1 or any(new.contains(r) for r in replaced):
        return DBIC_MIN
    return TIE_DBIC


# why blocked cross-validation cannot judge an effect (then the validation run does)
CV_CONFINED = "the effect lies within one training segment"
CV_OUT_OF_RANGE = "the effect lies where no training segment can be scored inside the others' range"
CV_NO_FOLD = "no training segment could be scored"


@dataclass
class Scored:
    effects: tuple[fx.Effect, ...]
    ssr: float
    rank: int
    n: int
    rho: float
    cv: float
    resid: np.ndarray = field(repr=False)

    @property
    def n_eff(self) -> float:
        rho = min(max(self.rho, 0.0), 0.95)
        return max(10.0, self.n * (1 - rho) / (1 + rho))


@dataclass
class SearchProblem:
    """The training run on the evidence grid: target, declared design, inputs on the fine grid."""

    yb: np.ndarray                 # (n_blocks,) 100-s means of the target
    Xb: np.ndarray                 # (n_blocks, k) 100-s means of the declared design
    fine: fx.Inputs                # inputs on the fine grid (10-s means)
    declared_signals_b: np.ndarray  # (n_blocks, s) 100-s means of the declared model's inputs
    families: list[fx.Family]
    n_eff_noise: float = 10.0      # effective n of the 100-s residual if it were noise alone (lower bound)
    # the declared model's own rate filter window (s): where the training run does not tell a rate
    # effect's window apart from it, the effect's rate is filtered alike (``settle_rate_windows``)
    rate_window_s: float | None = None
    fine_valid: np.ndarray | None = None   # fine-grid rows where the target was measured
    # the noise model (``noisefloor.NoiseModel``) of the full-rate training residual of a design with
    # these effects: the null hypothesis of the GLS gate (None: no GLS gate)
    noise_for: Callable[[tuple[fx.Effect, ...]], Any] | None = None
    _whiteners: dict[tuple, np.ndarray] = field(default_factory=dict, repr=False)
    _cache: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    _folds: list[tuple[np.ndarray, np.ndarray]] | None = field(default=None, repr=False)
    _projectors: dict[tuple[str, ...], "_Projector"] = field(default_factory=dict, repr=False)
    _ssrs: dict[tuple[str, ...], float] = field(default_factory=dict, repr=False)
    _plan: BlockPlan | None = field(default=None, repr=False)     # the evidence blocks of the fine grid

    def __post_init__(self) -> None:
        self.rows = np.isfinite(self.yb) & np.all(np.isfinite(self.Xb), axis=1)
        self.base_rank = _rank(self.Xb[self.rows])

    # ---------------------------------------------------------------- columns
    def columns(self, eff: fx.Effect) -> np.ndarray:
        """The effect's columns built on the fine grid, as 100-s evidence-block means."""
        key = eff.label
        got = self._cache.get(key)
        if got is None:
            cols = eff.columns(self.fine)
            if self.fine_valid is not None:
                # a block mean of a regressor over the same samples as the target's (a gap, e.g. the
                # gyro powered off, must not dilute the regressor's block mean only)
                cols = {k: np.where(self.fine_valid, v, np.nan) for k, v in cols.items()}
            if self._plan is None:
                self._plan = BlockPlan(self.fine.time, BLOCK_S)
            got = np.column_stack([self._plan.means(v) for v in cols.values()])
            self._cache[key] = got
        return got

    def lies_within(self, eff: fx.Effect, effects: list[fx.Effect] | tuple[fx.Effect, ...]) -> bool:
        """The effect's columns lie within the span of the declared design's and ``effects``' columns on
        the evidence blocks (to rounding): a model with it in their place is a restriction of theirs."""
        X, Z = self.design(tuple(effects)), self.columns(eff)
        ok = self.rows & np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(Z), axis=1)
        if not ok.any():
            return False
        left = Z[ok] - X[ok] @ np.column_stack([_lstsq(X[ok], z) for z in Z[ok].T])
        return bool(np.linalg.norm(left) <= SPAN_RTOL * np.linalg.norm(Z[ok]))

    def design(self, effects: tuple[fx.Effect, ...]) -> np.ndarray:
        if not effects:
            return self.Xb
        return np.column_stack([self.Xb] + [self.columns(e) for e in effects])

    # ---------------------------------------------------------------- fits
    def block_index(self) -> np.ndarray:
        """Each evidence block's number from the run's start (an outage keeps its lag)."""
        if self._plan is None:
            self._plan = BlockPlan(self.fine.time, BLOCK_S)
        tb = self._plan.time_s
        return np.round((tb - tb[0]) / BLOCK_S)

    def gls_p(self, base: tuple[fx.Effect, ...], X0: np.ndarray, X1: np.ndarray) -> float:
        """p of the GLS F test (``noisefloor.gls_f_test``) for the columns X1 adds to X0, under the
        noise model of the base design's training residual; 0 when there is no noise model."""
        from bench.fit.noisefloor import block_covariance, gls_f_test, gls_whitener

        if self.noise_for is None:
            return 0.0
        ok = self.rows & np.all(np.isfinite(X1), axis=1)
        key = (tuple(e.label for e in base), ok.tobytes())
        W = self._whiteners.get(key)
        if W is None:
            model = self.noise_for(base)
            if len(self._whiteners) > 32:
                self._whiteners.clear()
            W = self._whiteners[key] = gls_whitener(block_covariance(model, self.block_index()[ok]))
        return gls_f_test(W, X0[ok], X1[ok], self.yb[ok])[1]

    def ssr(self, effects: tuple[fx.Effect, ...]) -> float:
        """The training SSR of the declared design with ``effects`` added (kept per set of labels: the
        search asks for the same set again in its sweeps, pairs and exchanges)."""
        key = tuple(e.label for e in effects)
        got = self._ssrs.get(key)
        if got is None:
            if len(self._ssrs) > SSR_MEMO:
                self._ssrs.clear()
            got = self._ssrs[key] = self._ssr(effects)
        return got

    def ssr_each(self, others: tuple[fx.Effect, ...], candidates: Sequence[fx.Effect]) -> list[float]:
        """``ssr(others + (c,))`` for each candidate c, the candidates not yet kept projected together
        (one product with the design's basis for all of them: a scan over a grid or a kind's families)."""
        head = tuple(e.label for e in others)
        keys = [head + (c.label,) for c in candidates]
        out = [self._ssrs.get(k) for k in keys]
        todo = [i for i, v in enumerate(out) if v is None]
        if todo:
            got = self.projector(others).ssr_each([self.columns(candidates[i]) for i in todo])
            if len(self._ssrs) > SSR_MEMO:
                self._ssrs.clear()
            for i, v in zip(todo, got):
                out[i] = self._ssrs[keys[i]] = v if v is not None else self._ssr(others + (candidates[i],))
        return out

    def _ssr(self, effects: tuple[fx.Effect, ...]) -> float:
        if effects:
            got = self.projector(effects[:-1]).ssr_with(self.columns(effects[-1]))
            if got is not None:
                return got
        X = self.design(effects)
        ok = self.rows & np.all(np.isfinite(X), axis=1)
        r = self.yb[ok] - X[ok] @ _lstsq(X[ok], self.yb[ok])
        return float(r @ r)

    def projector(self, effects: tuple[fx.Effect, ...]) -> "_Projector":
        key = tuple(e.label for e in effects)
        got = self._projectors.get(key)
        if got is None:
            if len(self._projectors) > 64:
                self._projectors.clear()
            got = self._projectors[key] = _Projector(self.design(effects), self.yb, self.rows)
        return got

    def score(self, effects: tuple[fx.Effect, ...], with_cv: bool = True) -> Scored:
        X = self.design(effects)
        ok = self.rows & np.all(np.isfinite(X), axis=1)
        beta = _lstsq(X[ok], self.yb[ok])
        resid = np.full(len(self.yb), np.nan)
        resid[ok] = self.yb[ok] - X[ok] @ beta
        r = resid[ok]
        cv = self.cv(X) if with_cv else float("nan")
        return Scored(effects, float(r @ r), _rank(X[ok]), int(ok.sum()), lag1_autocorrelation(resid), cv, resid)

    def folds(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Contiguous segments of the training blocks; each is scored where the declared inputs lie
        inside the range of the other segments."""
        if self._folds is None:
            idx = np.flatnonzero(self.rows)
            edges = np.linspace(0, len(idx), CV_FOLDS + 1).astype(int)
            out = []
            S = self.declared_signals_b
            for a, b in zip(edges[:-1], edges[1:]):
                test = np.zeros(len(self.yb), dtype=bool)
                test[idx[a:b]] = True
                fit = self.rows & ~test
                if S.shape[1]:
                    lo = np.nanmin(S[fit], axis=0)
                    hi = np.nanmax(S[fit], axis=0)
                    with np.errstate(invalid="ignore"):
                        test &= np.all((S >= lo) & (S <= hi), axis=1)
                if test.sum() >= 2 and fit.sum() > 2 * self.Xb.shape[1]:
                    out.append((fit, test))
            self._folds = out
        return self._folds

    def cv(self, X: np.ndarray) -> float:
        finite = np.all(np.isfinite(X), axis=1)
        sse, cnt = 0.0, 0
        for fit, test in self.folds():
            f, t = fit & finite, test & finite
            if t.sum() == 0 or f.sum() <= X.shape[1]:
                continue
            beta = _lstsq(X[f], self.yb[f])
            e = self.yb[t] - X[t] @ beta
            sse += float(e @ e)
            cnt += int(t.sum())
        return sse / cnt if cnt else float("nan")

    def cv_gain(self, X0: np.ndarray, X1: np.ndarray) -> tuple[float, str]:
        """Relative drop of the cross-validated error from design X0 to X1 (X1 = X0 plus columns),
        over the folds where the added columns vary in the other segments (an effect confined to one
        segment, e.g. one warm-up, cannot be predicted from the others: those folds say nothing
        about it).  NaN when no fold can judge it (then the validation run does), with the reason."""
        k0 = X0.shape[1]
        finite = np.all(np.isfinite(X1), axis=1)
        added = X1[:, k0:] - np.nanmean(X1[finite][:, k0:], axis=0)
        energy = np.where(finite[:, None], added ** 2, 0.0).sum(axis=1)
        total = float(energy.sum())
        folds = self.folds()
        tested = np.zeros(len(energy), dtype=bool)
        for _fit, test in folds:
            tested |= test
        confined = [total > 0 and float(energy[test].sum()) > 0.5 * total for _fit, test in folds]
        if total > 0 and any(confined):
            return float("nan"), CV_CONFINED
        if total > 0 and float(energy[tested].sum()) < 0.5 * total:
            return float("nan"), CV_OUT_OF_RANGE
        sse0 = sse1 = 0.0
        for fit, test in folds:
            f, t = fit & finite, test & finite
            if t.sum() == 0 or f.sum() <= X1.shape[1]:
                continue
            for X, acc in ((X0, 0), (X1, 1)):
                e = self.yb[t] - X[t] @ _lstsq(X[f], self.yb[f])
                if acc == 0:
                    sse0 += float(e @ e)
                else:
                    sse1 += float(e @ e)
        return (1.0 - sse1 / sse0, "") if sse0 > 0 else (float("nan"), CV_NO_FOLD)

    # ---------------------------------------------------------------- parameter search
    def best_value(self, family: fx.Family, others: tuple[fx.Effect, ...],
                   refine_delay: bool = False) -> tuple[fx.Effect, float]:
        """The family's continuous parameter that minimises the training SSR with ``others`` fixed
        (grid, then bounded golden section between the grid neighbours; from an end of the grid, out
        to the family's bounds: the grid is where the scan starts, not a limit on the answer).  With
        ``refine_delay`` a memory's delay (``fx.Family.delayed``) is searched too, the parameter
        re-fitted at each delay tried (the joint re-fit of added effects; candidates are scanned at
        their family's current delay).  An optimum at the family's open upper limit
        (``fx.Family.open_end``) costs infinity: no place is filled by it."""
        eff, cost = self._best_delay(family, others) if refine_delay and family.delayed else \
            self._best_value(family, others)
        # an optimum at an open upper limit (``fx.Family.open_end``) is not the family's effect
        return (eff, float("inf")) if family.open_end(eff.value) else (eff, cost)

    def _best_delay(self, family: fx.Family, others: tuple[fx.Effect, ...]) -> tuple[fx.Effect, float]:
        """Profile over the memory's delay: on the grid ``fx.MEMORY_DELAYS_S`` (and the current delay)
        each delay with its parameter re-fitted near the current one (a later path is met by a smaller
        width), then bounded golden section between the best point's neighbours; the parameter is
        re-fitted in full at the delay chosen."""
        here, here_cost = self._best_value(family, others)
        tried: dict[float, tuple[float, float]] = {}       # delay -> (SSR, width)
        # the width stays within the range where it is meaningful (``fx.Family.bounds``) at every delay
        lw = np.log(here.value)
        low, high = (np.log(b) for b in family.bounds)
        span = (min(lw, max(lw - DELAY_PROFILE_SPAN, low)), max(lw, min(lw + DELAY_PROFILE_SPAN, high)))

        def at(d: float) -> float:
            d = float(round(d))
            if d not in tried:
                f = family.with_delay(d)
                res = minimize_scalar(lambda v: self.ssr(others + (f.at(float(np.exp(v))),)),
                                      bounds=span, method="bounded", options={"xatol": 0.03})
                tried[d] = (float(res.fun), float(np.exp(res.x)))
            return tried[d][0]

        grid = sorted(set(fx.MEMORY_DELAYS_S) | {family.delay_s})
        costs = [at(d) for d in grid]
        i = int(np.argmin(costs))
        lo_lim, hi_lim = fx.MEMORY_DELAY_LIMITS_S
        lo = grid[i - 1] if i > 0 else lo_lim
        hi = grid[i + 1] if i + 1 < len(grid) else hi_lim
        if hi > lo:
            minimize_scalar(at, bounds=(lo, hi), method="bounded", options={"xatol": 2.0})
        best = min(tried, key=lambda d: tried[d][0])
        # the width re-fitted in full at the delay chosen; the profile's own width when that is better
        full = self._best_value(family.with_delay(best), others)
        profiled = (family.with_delay(best).at(tried[best][1]), tried[best][0])
        return min((here, here_cost), full, profiled, key=lambda r: r[1])

    def grid_ssr(self, family: fx.Family, others: tuple[fx.Effect, ...]) -> float:
        """The family's lowest training SSR over its scan grid, ``others`` held: how well it could fill a
        place, before any refinement (the coarse ranking of swaps and exchanges)."""
        return min(self.ssr_each(others, family.grid_effects))

    def grid_bic(self, family: fx.Family, others: tuple[fx.Effect, ...], n_eff: float) -> float:
        """The family's lowest training BIC over its scan grid, ``others`` held (the coarse pass of a
        re-fit over a kind's probes, pairs and forms)."""
        cands = family.grid_effects
        # one family: the same columns and penalty at every grid value, so the lowest BIC is at the lowest SSR
        return self.bic(others + (cands[0],), n_eff, min(self.ssr_each(others, cands)))

    def _best_value(self, family: fx.Family, others: tuple[fx.Effect, ...]) -> tuple[fx.Effect, float]:
        if not family.param:
            eff = family.at(None)
            return eff, self.ssr(others + (eff,))
        grid = list(family.grid)
        costs = self.ssr_each(others, family.grid_effects)
        i = int(np.argmin(costs))
        low, high = family.bounds
        lo = np.log(grid[i - 1] if i > 0 else min(low, grid[0]))
        hi = np.log(grid[i + 1] if i + 1 < len(grid) else max(high, grid[-1]))
        res = minimize_scalar(lambda lv: self.ssr(others + (family.at(float(np.exp(lv))),)),
                              bounds=(lo, hi), method="bounded", options={"xatol": 0.03})
        if np.isfinite(res.fun) and res.fun < costs[i]:
            return family.at(float(np.exp(res.x))), float(res.fun)
        return family.grid_effects[i], float(costs[i])

    def refit_jointly(self, effects: tuple[fx.Effect, ...]) -> tuple[fx.Effect, ...]:
        """Joint re-fit of every added effect's nonlinear parameters (a memory's delay included), then
        swaps."""
        return self.swap(self.refit_params(effects, refine_delay=True))

    def refit_params(self, effects: tuple[fx.Effect, ...], keep_families: bool = False,
                     refine_delay: bool = False) -> tuple[fx.Effect, ...]:
        """Coordinate sweeps: each added effect's probe/pair/form and parameter re-chosen within its
        kind with the others held (``keep_families``: only the continuous parameters; ``refine_delay``:
        an added memory's delay profiled too, other families at their current delay)."""
        current = tuple(effects)
        n_eff = self.score(current, with_cv=False).n_eff
        best = self.bic(current, n_eff)
        for _ in range(JOINT_SWEEPS):
            changed = False
            for i, eff in enumerate(current):
                others = current[:i] + current[i + 1:]
                fams = [eff.family] if keep_families else \
                    [eff.family if f == eff.family else f for f in self.families
                     if f.kind == eff.kind and not any(o.family == f for o in others)]
                if len(fams) > 1:        # coarse pass over the kind's probes/pairs/forms, refine the best two
                    coarse = sorted(fams, key=lambda f: self.grid_bic(f, others, n_eff))
                    fams = coarse[:2]
                    if refine_delay and eff.family.delayed and eff.family not in fams:
                        fams.append(eff.family)      # a memory in place always has its delay profiled
                for fam in fams:
                    # the memory's delay is profiled for the family in place (the others at its current delay)
                    cand, cost = self.best_value(fam, others, refine_delay=refine_delay and fam == eff.family)
                    if not np.isfinite(cost):
                        continue
                    trial = others[:i] + (cand,) + others[i:]
                    b = self.bic(trial, n_eff)
                    # BIC: another form or probe pays for its columns, and moves the choice only beyond
                    # its margin
                    if b < best - max(replacement_margin(fam, (eff.family,)), 1e-9):
                        current, best, eff, changed = trial, b, cand, True
            if not changed:
                break
        return current

    def bic(self, effects: tuple[fx.Effect, ...], n_eff: float, ssr: float | None = None) -> float:
        """The training BIC of the design with ``effects`` at effective n ``n_eff`` (``ssr``: their
        training SSR when it is known)."""
        k = sum(self.columns(e).shape[1] for e in effects)
        ssr = self.ssr(effects) if ssr is None else ssr
        return (n_eff * np.log(max(ssr, 1e-300)) + k * np.log(n_eff)
                + sum(e.family.penalty(n_eff) for e in effects))

    def swap(self, effects: tuple[fx.Effect, ...]) -> tuple[fx.Effect, ...]:
        """Replace an added effect by another family (any kind) when that lowers the BIC (effective n
        of the current model) by more than ``replacement_margin``: an early choice made while another
        effect was still missing is revisited once that effect is in.  A lone effect is left as chosen:
        it was ranked against every family at its step."""
        current = tuple(effects)
        if len(current) < 2:
            return current
        n_eff = self.score(current, with_cv=False).n_eff
        for i in range(len(current)):
            others = current[:i] + current[i + 1:]
            best_bic = self.bic(current, n_eff)
            fams = [f for f in self.families if not any(o.family == f for o in current)]
            coarse = sorted(((self.grid_ssr(f, others), f) for f in fams), key=lambda c: c[0])
            for _, fam in coarse[:3]:
                cand, cost = self.best_value(fam, others)
                if not np.isfinite(cost):
                    continue
                trial = others[:i] + (cand,) + others[i:]
                b = self.bic(trial, n_eff)
                if b < best_bic - replacement_margin(cand.family, (current[i].family,)):
                    current, best_bic = trial, b
        return current


class _Projector:
    """Frisch-Waugh-Lovell: the residual of y and of new columns after the current design, so the
    sum of squares with a few added columns costs a projection, not a full least squares."""

    def __init__(self, X: np.ndarray, y: np.ndarray, rows: np.ndarray) -> None:
        self.ok = rows & np.all(np.isfinite(X), axis=1)
        Xo = X[self.ok]
        scale = np.sqrt(np.mean(Xo ** 2, axis=0))
        scale[~(scale > 0)] = 1.0
        u, sv, _ = np.linalg.svd(Xo / scale, full_matrices=False)
        self.q = u[:, sv > sv[0] * 1e-10] if len(sv) else u[:, :0]
        yo = y[self.ok]
        self.yr = yo - self.q @ (self.q.T @ yo)
        self.yy = float(self.yr @ self.yr)

    def ssr_each(self, Zs: list[np.ndarray]) -> list[float | None]:
        """``ssr_with`` of each Z, the projection of all of them done in one product."""
        widths = [Z.shape[1] for Z in Zs]
        Zo = np.column_stack(Zs)[self.ok]
        Zr = Zo - self.q @ (self.q.T @ Zo)
        starts = np.cumsum([0] + widths[:-1])
        out: list[float | None] = [None] * len(Zs)
        # one-column candidates all at once (``_ssr_of``'s steps, column by column)
        one = [i for i, w in enumerate(widths) if w == 1]
        if one:
            cols = starts[one]
            A, R = Zo[:, cols], Zr[:, cols]
            finite = np.isfinite(A).all(axis=0)
            norms = np.sqrt(np.einsum("ij,ij->j", R, R))
            keep = norms > 1e-9 * np.maximum(1.0, np.sqrt(np.einsum("ij,ij->j", A, A)))
            with np.errstate(invalid="ignore", divide="ignore"):
                W = R / norms
                g = np.einsum("ij,ij->j", W, W)
                c = W.T @ self.yr
                ssr = np.maximum(self.yy - c ** 2 / g, 0.0)
            for k, i in enumerate(one):
                if finite[k]:
                    out[i] = float(ssr[k]) if keep[k] else self.yy
        for i, w in enumerate(widths):
            if w != 1:
                out[i] = self._ssr_of(Zo[:, starts[i]:starts[i] + w], Zr[:, starts[i]:starts[i] + w])
        return out

    def ssr_with(self, Z: np.ndarray) -> float | None:
        Zo = Z[self.ok]
        return self._ssr_of(Zo, Zo - self.q @ (self.q.T @ Zo))

    def _ssr_of(self, Zo: np.ndarray, Zr: np.ndarray) -> float | None:
        """The SSR with the columns Zo (rows of the design) added, Zr their residual after it; None
        when a value is missing."""
        if not np.isfinite(Zo).all():
            return None
        norms = np.sqrt(np.einsum("ij,ij->j", Zr, Zr))
        keep = norms > 1e-9 * max(1.0, float(np.sqrt(np.einsum("ij,ij->", Zo, Zo))))
        if not keep.any():
            return self.yy
        W = Zr[:, keep] / norms[keep]
        # the few added columns: their own small Gram matrix (eigen-decomposed, rank-revealing like
        # the pseudo-inverse) instead of a general least-squares call per candidate
        g = W.T @ W
        c = W.T @ self.yr
        if g.shape == (1, 1):
            # one column: its 1x1 Gram matrix is its own eigenvalue (the same numbers, without the call)
            return max(float(self.yy - np.sum(c ** 2 / g[0])), 0.0)
        lam, v = np.linalg.eigh(g)
        good = lam > lam[-1] * 1e-10
        proj = v[:, good].T @ c
        return max(float(self.yy - np.sum(proj ** 2 / lam[good])), 0.0)


def evidence_blocks(fine_time: np.ndarray, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """100-s evidence blocks of fine-grid columns (``bench.signal.block_means``); the same fine time
    axis always gives the same blocks, so target, design and effect columns line up."""
    return block_means(fine_time, {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}, BLOCK_S).columns


def hac_wald_p(X: np.ndarray, y: np.ndarray, columns: list[int]) -> float:
    """p-value of ``bench.signal.hac_wald_test`` (1 when the robust covariance is singular), with
    sqrt(n) Newey-West lags when that is more than the default: residuals with flicker (1/f) noise
    keep their correlation far longer than the default lag count assumes."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")       # rank-deficient candidates: judged by the p-value
            n = int(np.sum(np.all(np.isfinite(X), axis=1) & np.isfinite(y)))
            return hac_wald_test(X, y, columns, maxlags=max(newey_west_lags(n), int(np.ceil(np.sqrt(n))))).p_value
    except (np.linalg.LinAlgError, ValueError):
        return 1.0


def _lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The search's small dense solve (hundreds of rows, called thousands of times: no per-call
    thread-pool set-up); full-rate fits use ``bench.signal.lstsq``."""
    scale = np.sqrt(np.mean(X ** 2, axis=0)) if len(X) else np.ones(X.shape[1])
    scale[~(scale > 0)] = 1.0
    beta, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    return beta / scale


def _rank(X: np.ndarray) -> int:
    if len(X) == 0:
        return 0
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    return int(np.linalg.matrix_rank(X / np.where(scale > 0, scale, 1.0), tol=None))


def gates(problem: SearchProblem, base: Scored, new: Scored, added: tuple[fx.Effect, ...],
          with_gls: bool = True) -> dict[str, Any]:
    """The pieces of training evidence for adding ``added`` to ``base`` (giving ``new``); without
    ``with_gls`` (the backward pass, which judges redundancy on BIC alone) the GLS test is skipped."""
    rank_gain = new.rank - base.rank
    # the residual's own autocorrelation counts structure that other effects still have to explain as
    # if it were noise; the noise model's autocorrelation of 100-s means bounds n_eff from below
    n_eff = max(new.n_eff, problem.n_eff_noise)
    if rank_gain <= 0 or new.ssr <= 0 or new.ssr >= base.ssr:
        dbic = -np.inf
    else:
        dbic = (n_eff * np.log(base.ssr / new.ssr) - rank_gain * np.log(n_eff)
                - sum(e.family.penalty(n_eff) for e in added))
    X = problem.design(new.effects)
    k0 = problem.design(base.effects).shape[1]
    p = hac_wald_p(X[problem.rows], problem.yb[problem.rows], list(range(k0, X.shape[1]))) if dbic > DBIC_MIN else 1.0
    X0 = problem.design(base.effects)
    cv_gain, cv_note = problem.cv_gain(X0, X)
    cv_ok = (not np.isfinite(cv_gain)) or cv_gain >= MIN_CV_GAIN
    # the GLS F test under the noise model's own covariance of block means (white and flicker terms of
    # the base design's residual), judged only for what passed the other gates.  The candidate is the
    # best of every family the step tried: its p is held to P_MAX / (number of families) (Bonferroni:
    # the chance that the best of m noise-only candidates passes stays below P_MAX)
    judged = with_gls and dbic > DBIC_MIN and p < P_MAX and cv_ok
    p_gls = problem.gls_p(base.effects, X0, X) if judged else float("nan")
    passed = bool(dbic > DBIC_MIN and p < P_MAX and cv_ok and (not with_gls or p_gls < P_MAX / max(1, len(problem.families))))
    out = {"delta_bic": float(dbic), "hac_wald_p": float(p), "cv_gain": float(cv_gain), "n_blocks": new.n,
           "n_eff": float(n_eff), "block_s": BLOCK_S, "cv_folds": len(problem.folds()), "passed": passed}
    if np.isfinite(p_gls):
        out["gls_f_p"] = float(p_gls)
    if cv_note:
        out["cv_not_applicable"] = cv_note
    return out


def cv_gain_text(evidence: dict[str, Any]) -> str:
    """The cross-validation entry of an effect's evidence, in words: the drop of the cross-validated
    error, or "n/a (why)" when blocked cross-validation could not judge the effect."""
    gain = evidence.get("cv_gain")
    if isinstance(gain, (int, float)) and np.isfinite(gain):
        return f"-{100 * gain:.0f} %"
    return f"n/a ({evidence.get('cv_not_applicable') or CV_NO_FOLD})"


def search(problem: SearchProblem, stop_std100: float | None = None,
           stop_at: Callable[[tuple[fx.Effect, ...]], float] | None = None,
           white_at: Callable[[tuple[fx.Effect, ...]], bool] | None = None) -> tuple[tuple[fx.Effect, ...], list[dict[str, Any]]]:
    """Forward selection with pair look-ahead, joint re-fits and swaps.  Returns the chosen effects
    and the evidence of each step (what was added, its gates, the runner-up).

    Candidates are ranked by the BIC of the model they give, all with one effective n (that of the
    whitest candidate model of the step), so that a candidate does not win by whitening its own
    residual; each must pass the gates with its own effective n.  Pairs of the strongest families are
    fitted jointly at every step; a pair is taken instead of the best single when its BIC is lower by
    more than ``PAIR_DBIC`` (two effects at once that no single one explains well).  When a pair passes
    and the step's pick leaves the training residual above its floor, triples of the same pool are
    fitted too; one is taken in the pick's place on the same terms, and only when it brings the training
    residual to its floor and leaves it white under its noise model (``white_at``; effects whose
    contributions partly cancel on the run).  The search stops
    at the training noise floor (``stop_std100``, then ``stop_at`` of the effects chosen), unless the
    single addition the step would make lowers that floor by more than ``AT_FLOOR_RATIO``."""
    chosen: tuple[fx.Effect, ...] = ()
    steps: list[dict[str, Any]] = []
    while len(chosen) < MAX_EFFECTS:
        base = problem.score(chosen)
        left = float(np.nanstd(base.resid, ddof=1))
        # once effects are in, the floor is read from the residual it judges (``stop_at``)
        floor_from_residual = bool(chosen) and stop_at is not None
        if floor_from_residual:
            stop_std100 = stop_at(chosen)
        at_floor = stop_std100 is not None and left <= stop_std100
        if at_floor and not floor_from_residual:
            steps.append(_stopped(left, stop_std100))
            break
        used = {e.family for e in chosen}
        singles = []
        for fam in problem.families:
            if fam in used:
                continue
            eff, s = problem.best_value(fam, chosen)
            if s < base.ssr:
                singles.append((s, eff))
        singles.sort(key=lambda t: t[0])
        ranked = []
        for s, eff in singles[:SCORED_SINGLES]:
            new = problem.score(chosen + (eff,))
            ranked.append(((eff,), new, gates(problem, base, new, (eff,))))
        pairs = []
        if not at_floor and len(chosen) + 2 <= MAX_EFFECTS:
            pool, kinds = [], set()
            for _, eff in singles:              # the strongest family of each kind
                if eff.kind not in kinds and len(pool) < PAIR_POOL:
                    pool.append(eff)
                    kinds.add(eff.kind)
            pairs = _joint_moves(problem, chosen, base, pool, 2)
        everything = ranked + pairs
        if not everything:
            break
        n_ref = max(r[1].n_eff for r in everything)
        bic = {id(r): problem.bic(chosen + r[0], n_ref) for r in everything}
        passing = sorted((r for r in ranked if r[2]["passed"]), key=lambda r: bic[id(r)])
        passing_pairs = sorted((r for r in pairs if r[2]["passed"]), key=lambda r: bic[id(r)])
        pick = passing[0] if passing else None
        if pick is not None:
            # candidates within TIE_DBIC of the best are a tie the data cannot break ("not worth more
            # than a bare mention"): the one with the fewest searched parameters and choices is taken
            ties = [r for r in passing if bic[id(r)] - bic[id(pick)] < TIE_DBIC]
            pick = min(ties, key=lambda r: (r[0][0].family.n_nonlinear, bic[id(r)]))
            # a richer form of an effect is taken over its simpler form only on strong evidence
            simpler = [r for r in passing if pick[0][0].family.contains(r[0][0].family)
                       and bic[id(r)] - bic[id(pick)] < DBIC_MIN]
            if simpler:
                pick = simpler[0]
        if passing_pairs and (pick is None or (bic[id(passing_pairs[0])] < bic[id(pick)] - PAIR_DBIC
                                               and passing_pairs[0][1].cv < pick[1].cv * (1 - MIN_CV_GAIN)
                                               and not _at_floor(pick, chosen, stop_at))):
            pick = passing_pairs[0]
        passing_triples = []
        if (passing_pairs and len(chosen) + 3 <= MAX_EFFECTS and pick is not None
                and not _at_floor(pick, chosen, stop_at)):
            # three effects whose contributions partly cancel on the training run (a warm-up, a drift
            # and a gradient that follows the run's course) can each fit little alone or in pairs and
            # all of it together: once a pair shows there is more than one effect and the step's pick
            # leaves the training residual above its floor, triples are fitted too
            passing_triples = [r for r in _joint_moves(problem, chosen, base, pool, 3)
                               if r[2]["passed"]]
        if passing_triples:
            # compared at the effective n of the whitest of them all
            n3 = max(n_ref, max(r[1].n_eff for r in passing_triples))
            best3 = min(passing_triples, key=lambda r: problem.bic(chosen + r[0], n3))
            # three effects taken in one step must account for the whole training residual (down to its
            # noise floor): three bent to share a driver no candidate models fit some of it, not all.
            # That floor is read from the residual they leave, and what they leave of such a driver lifts
            # its flicker term; the structure shows in the residual's block means, which the noise model
            # does not whiten
            if (problem.bic(chosen + best3[0], n3) < problem.bic(chosen + pick[0], n3) - PAIR_DBIC
                    and best3[1].cv < pick[1].cv * (1 - MIN_CV_GAIN) and _at_floor(best3, chosen, stop_at)
                    and (white_at is None or white_at(chosen + best3[0]))):
                pick = (_simplest_of_ties(problem, chosen, best3[0]),) + best3[1:]
                bic[id(pick)] = problem.bic(chosen + pick[0], n_ref)
        if at_floor and (pick is None or not stop_at(chosen + pick[0]) * AT_FLOOR_RATIO < stop_std100):
            # the floor the residual is judged against is read from that residual, and slow structure
            # still in it reads as flicker noise and lifts it: the search goes on at the floor only when
            # the addition it would make lowers that floor beyond the verdict's tolerance
            steps.append(_stopped(left, stop_std100))
            break
        if pick is None:
            break
        move, new, ev = pick
        ev["pair"] = len(move) == 2
        if len(move) == 3:
            ev["triple"] = True
        runner = next((r for r in passing if r is not pick and r[0][0].family != move[0].family), None)
        ev["runner_up"] = _describe(runner[0][0], runner[2]) if runner else None
        ev["bic_margin_to_runner_up"] = float(bic[id(runner)] - bic[id(pick)]) if runner else None
        picked = {m.family for m in move}
        # single additions of this step alike in training BIC; a joint move's look-alikes are its members'
        # (``lookalikes`` on the final model): a single addition's BIC says nothing about a pair's
        ev["ambiguous_with"] = [{**_describe(r[0][0], r[2]), "bic_margin": float(bic[id(r)] - bic[id(pick)])}
                                for r in passing if r is not pick and r[0][0].family not in picked
                                and bic[id(r)] - bic[id(pick)] < AMBIGUOUS_DBIC] if len(move) == 1 else []
        chosen = problem.refit_jointly(chosen + move)
        steps.append({"added": [e.label for e in move], "added_families": [e.family.label for e in move],
                      "evidence": ev, "train_std100_before_step": left,
                      "after_joint_refit": [e.label for e in chosen],
                      **({"floor_inflated": {"stop_std100_dph": stop_std100,
                                             "stop_std100_with_it_dph": stop_at(chosen)}}
                         if at_floor else {})})
    chosen = exchange(problem, chosen, steps)
    chosen = prune(problem, chosen, steps)
    chosen = centre_stepwise(problem, drop_drift_that_is_a_step(problem, chosen, steps))
    settled = settle_rate_windows(problem, chosen)
    moved = [{"effect": a.label, "window_s": b.value, "declared_rate_window_s": problem.rate_window_s}
             for a, b in zip(chosen, settled) if a.value != b.value]
    if moved:
        steps.append({"rate_window_settled": moved})
    return settled, steps


def _joint_moves(problem: SearchProblem, chosen: tuple[fx.Effect, ...], base: Scored, pool: list[fx.Effect],
                 size: int) -> list[tuple[tuple[fx.Effect, ...], Scored, dict[str, Any]]]:
    """Every ``size`` effects of ``pool`` (distinct families) added to ``chosen`` together, their
    nonlinear parameters re-fitted jointly: the move, its score and its gates (each added effect's own
    HAC Wald p below ``P_MAX`` too)."""
    out = []
    for combo in combinations(pool, size):
        if len({e.family for e in combo}) < size:
            continue
        move = problem.refit_params(chosen + combo)[len(chosen):]
        new = problem.score(chosen + move)
        ev = gates(problem, base, new, move)
        if ev["passed"]:
            each = [hac_wald_p(*_xy(problem, chosen + move), _cols_of(problem, chosen + move, j))
                    for j in range(len(chosen), len(chosen) + size)]
            ev["each_hac_wald_p"] = each
            ev["passed"] = max(each) < P_MAX
        if ev["passed"] and problem.noise_for is not None:
            # and each its own GLS F test, the others in, under the noise model of the whole move's
            # residual (as its HAC Wald test is judged on that residual), at a single addition's level:
            # a time drift taken beside a strong effect can be a wander of flicker noise that HAC, with
            # its few lags, reads as significant
            full = chosen + move
            each_gls = []
            for j in range(size):
                without = chosen + move[:j] + move[j + 1:]
                each_gls.append(problem.gls_p(full, problem.design(without), problem.design(without + (move[j],))))
            ev["each_gls_f_p"] = each_gls
            ev["passed"] = max(each_gls) < P_MAX / max(1, len(problem.families))
        out.append((move, new, ev))
    return out


def _simplest_of_ties(problem: SearchProblem, chosen: tuple[fx.Effect, ...],
                      move: tuple[fx.Effect, ...]) -> tuple[fx.Effect, ...]:
    """Each effect of a joint move in turn: a family of its kind with fewer searched parameters
    (``fx.Family.n_nonlinear``: the own probe's lag in place of another probe's) whose fit in its place,
    the others held, the training BIC cannot tell from it (within ``TIE_DBIC``) is taken instead, as the
    search's tie rule does for a single addition.  The effects of a joint move start from the strongest
    family of each kind alone, and a re-fit moves a family only beyond a tie."""
    current = tuple(move)
    n_eff = problem.score(chosen + current, with_cv=False).n_eff
    for i, eff in enumerate(current):
        others = chosen + current[:i] + current[i + 1:]
        here = problem.bic(chosen + current, n_eff)
        best: tuple[tuple[int, float], tuple[fx.Effect, ...]] | None = None
        for fam in problem.families:
            if (fam.kind != eff.kind or fam.n_nonlinear >= eff.family.n_nonlinear
                    or any(o.family == fam for o in others)):
                continue
            cand, cost = problem.best_value(fam, others)
            if not np.isfinite(cost):
                continue
            trial = current[:i] + (cand,) + current[i + 1:]
            b = problem.bic(chosen + trial, n_eff)
            if b - here < TIE_DBIC and (best is None or (fam.n_nonlinear, b) < best[0]):
                best = ((fam.n_nonlinear, b), trial)
        if best is not None:
            current = best[1]
    return current


def exchange(problem: SearchProblem, effects: tuple[fx.Effect, ...],
             steps: list[dict[str, Any]]) -> tuple[fx.Effect, ...]:
    """Exchange pass on TRAIN once the forward selection is done.  A move takes one chosen effect out, or
    two (a merge), and puts one in its place: the others' parameters as they stand and re-fitted without
    what is taken out, the families that best fill the place (any kind, ``EXCHANGE_CANDIDATES`` of them
    by training SSR) tried with every continuous parameter re-fitted jointly.  The move that lowers the
    BIC most (effective n of the current model), beyond its ``replacement_margin``, is made, and the pass
    repeats.
    Forward selection commits to its first choices: an early effect bent to stand in for one still
    missing (a lag with a time constant beyond the run standing in for a time drift) keeps the later
    choices on the wrong probe, and two effects may share what one missing effect explains."""
    current = tuple(effects)
    if len(current) < 2:
        return current
    for _ in range(EXCHANGE_ROUNDS):
        n_eff = problem.score(current, with_cv=False).n_eff
        here = problem.bic(current, n_eff)
        best: tuple[float, tuple[int, ...], tuple[fx.Effect, ...]] | None = None    # dBIC, taken out, new set
        outs = [(i,) for i in range(len(current))] + list(combinations(range(len(current)), 2))
        for out in outs:
            removed = [current[i] for i in out]
            kept = tuple(e for i, e in enumerate(current) if i not in out)
            # a parameter bent to share the work of what is taken out, or bent once it is gone, hides the
            # family that fills the place: both starts are tried
            refitted = problem.refit_params(kept, keep_families=True)
            starts = (kept, refitted) if refitted != kept else (kept,)
            taken = {e.family for e in kept} | ({removed[0].family} if len(out) == 1 else set())
            coarse = sorted((min(problem.grid_ssr(f, h) for h in starts), k)
                            for k, f in enumerate(problem.families) if f not in taken)
            at = out[0]
            for _s, k in coarse[:EXCHANGE_CANDIDATES]:
                fam = problem.families[k]
                for held in starts:
                    cand, cost = problem.best_value(fam, held)
                    if not np.isfinite(cost):
                        continue
                    margin = replacement_margin(fam, tuple(r.family for r in removed),
                                                restriction=len(removed) > 1 and problem.lies_within(cand, removed))
                    trial = problem.refit_params(held[:at] + (cand,) + held[at:], keep_families=True)
                    gain = here - problem.bic(trial, n_eff)
                    if gain > margin and (best is None or gain > best[0]):
                        best = (gain, out, trial)
        if best is None:
            break
        gain, out, trial = best
        steps.append({"exchanged": [current[i].label for i in out], "for": trial[out[0]].label,
                      "delta_bic": float(gain), "after_exchange": [e.label for e in trial]})
        current = trial
    return current


def lookalikes(problem: SearchProblem, effects: tuple[fx.Effect, ...]) -> list[list[dict[str, Any]]]:
    """Per chosen effect, the candidates the training run cannot tell from it in the final model: a
    family not chosen (``LOOKALIKE_CANDIDATES`` of them, by training SSR on their grids) put in its place,
    its parameter fitted with the others held as they stand, within ``AMBIGUOUS_DBIC`` of the final
    model's training BIC (its effective n).  ``bic_margin`` is how far behind it is (negative: ahead, kept
    out by the tie or exchange margins).  A gradient between two nodes the same air drives can follow a
    lag or a rate of one of them this closely: the data name both, not one."""
    if not effects:
        return []
    n_eff = problem.score(effects, with_cv=False).n_eff
    here = problem.bic(effects, n_eff)
    taken = {e.family for e in effects}
    out = []
    for i in range(len(effects)):
        others = effects[:i] + effects[i + 1:]
        # a richer or simpler form of the same effect (``fx.Family.nests``) is that effect, not a look-alike
        own = effects[i].family
        coarse = sorted((problem.grid_ssr(f, others), k) for k, f in enumerate(problem.families)
                        if f not in taken and not (f.contains(own) or own.contains(f)))
        without = problem.bic(others, n_eff)
        found = []
        for _s, k in coarse[:LOOKALIKE_CANDIDATES]:
            cand, cost = problem.best_value(problem.families[k], others)
            if not np.isfinite(cost):
                continue
            trial = problem.bic(others[:i] + (cand,) + others[i:], n_eff)
            if trial - here < AMBIGUOUS_DBIC:
                found.append({"kind": cand.kind, "params": cand.params, "delta_bic": float(without - trial),
                              "bic_margin": float(trial - here)})
        out.append(sorted(found, key=lambda a: a["bic_margin"]))
    return out


def settle_rate_windows(problem: SearchProblem, effects: tuple[fx.Effect, ...]) -> tuple[fx.Effect, ...]:
    """A rate effect's filter window (``fx.RATE_WINDOW_PARAM``) that the training run does not tell
    apart from the declared model's own (``SearchProblem.rate_window_s``: the training BIC, its effective
    n, within ``TIE_DBIC`` of the best window's, the others held) is the declared one; otherwise the
    window nearest it, in log scale, that the training run still cannot tell from the best.  A window is
    a smoothing of the readings, not a physical constant: where the run cannot pin it, the scan's
    minimum is set by the noise, and a validation run with steeper ramps or a noisier rate pays for it."""
    target = problem.rate_window_s
    if target is None or not effects:
        return effects
    out = list(effects)
    n_eff = problem.score(tuple(out), with_cv=False).n_eff
    for i, e in enumerate(out):
        if e.family.param != fx.RATE_WINDOW_PARAM or e.value is None or e.value <= 0:
            continue
        lo_lim, hi_lim = e.family.bounds
        goal = float(np.clip(target, lo_lim, hi_lim))
        others = tuple(out[:i] + out[i + 1:])
        best = problem.ssr(tuple(out))
        if not (np.isfinite(best) and best > 0):
            continue

        def alike(w: float, fam=e.family, others=others, best=best) -> bool:
            got = problem.ssr(others + (fam.at(w),))
            return bool(np.isfinite(got) and n_eff * np.log(got / best) < TIE_DBIC)

        if alike(goal):
            out[i] = e.family.at(goal)
            continue
        inside = _last_alike(lambda lw: alike(float(np.exp(lw))), np.log(e.value), np.log(goal))
        if abs(inside - np.log(e.value)) > 1e-9:
            out[i] = e.family.at(float(np.exp(inside)))
    return tuple(out)


# relative change of the training SSR below which two parameter values fit the training run alike
SAME_FIT_RTOL = 1e-9
CENTRE_START_STEP = 0.005      # ln units: the first step out from the value chosen
EDGE_BISECTIONS = 8


def _last_alike(alike: Callable[[float], bool], inside: float, outside: float) -> float:
    """The edge between ``inside``, where ``alike`` holds, and ``outside``, where it does not (ln units),
    bisected ``EDGE_BISECTIONS`` times: the value nearest ``outside`` found alike."""
    for _ in range(EDGE_BISECTIONS):
        mid = 0.5 * (inside + outside)
        if alike(mid):
            inside = mid
        else:
            outside = mid
    return inside


def centre_stepwise(problem: SearchProblem, effects: tuple[fx.Effect, ...]) -> tuple[fx.Effect, ...]:
    """A stepwise parameter (``fx.Family.stepwise``: a relay's threshold) at the middle, in log scale,
    of the interval of values that fit the training run exactly alike (the others fixed).  The search
    lands anywhere in that interval (a grid value, where a golden section stopped); the training run
    cannot tell its values apart, and a validation run whose rates fall inside it switches the relay
    differently for each: the middle is the value furthest from both ends the data allow."""
    out = list(effects)
    for i, e in enumerate(out):
        if not (e.family.stepwise and e.value is not None and e.value > 0):
            continue
        others = tuple(out[:i] + out[i + 1:])
        cost = problem.ssr(tuple(out))
        if not np.isfinite(cost):
            continue

        def alike(lv: float, fam=e.family) -> bool:
            c = problem.ssr(others + (fam.at(float(np.exp(lv))),))
            return bool(np.isfinite(c) and abs(c - cost) <= SAME_FIT_RTOL * max(abs(cost), 1e-300))

        lv0 = float(np.log(e.value))
        lo_lim, hi_lim = (float(np.log(b)) for b in e.family.bounds)
        edges = []
        for sign, limit in ((-1.0, lo_lim), (1.0, hi_lim)):
            inside, step = lv0, CENTRE_START_STEP
            outside = None
            while outside is None:
                nxt = inside + sign * step
                if sign * (nxt - limit) >= 0:
                    if alike(limit):
                        inside = limit
                        break
                    outside = limit
                elif alike(nxt):
                    inside, step = nxt, 2.0 * step
                else:
                    outside = nxt
            if outside is not None:
                inside = _last_alike(alike, inside, outside)
            edges.append(inside)
        centre = 0.5 * (edges[0] + edges[1])
        if abs(centre - lv0) > CENTRE_START_STEP:
            out[i] = e.family.at(float(np.exp(centre)))
    return tuple(out)


# the change point of a bias step is looked for away from the run's ends (a step in the first or last
# few blocks is a level difference of a handful of points, which any slow term also fits)
STEP_EDGE_BLOCKS = 5


def drop_drift_that_is_a_step(problem: SearchProblem, effects: tuple[fx.Effect, ...],
                              steps: list[dict[str, Any]]) -> tuple[fx.Effect, ...]:
    """A time drift kept to describe what is in fact one abrupt change.  ``time_drift`` is a steady
    change with time (ageing); a bias step at one instant (a mode hop, a shock, a connector) is not
    driven by anything recorded, so it is no library effect.  A step (one column, 0 before and 1
    after; its time searched over every evidence block away from the ends and charged as a searched
    parameter) is fitted in the drift's place with the other effects held; when it beats the drift by
    more than ``DBIC_MIN`` in BIC (strong evidence, the search's own bar) the time structure is a
    step: the drift is left out and the step is reported as structure no recorded input explains."""
    drift = [i for i, e in enumerate(effects) if e.kind == "time_drift"]
    if not drift:
        return effects
    if problem._plan is None:
        problem._plan = BlockPlan(problem.fine.time, BLOCK_S)
    tb = problem._plan.time_s
    if len(tb) < 4 * STEP_EDGE_BLOCKS:
        return effects
    i = drift[0]
    others = effects[:i] + effects[i + 1:]
    n_eff = problem.score(effects, with_cv=False).n_eff
    proj = problem.projector(others)
    t = problem.fine.time
    valid = problem.fine_valid if problem.fine_valid is not None else np.ones(len(t), dtype=bool)
    best = (np.inf, 0.0, None)
    for t0 in tb[STEP_EDGE_BLOCKS:-STEP_EDGE_BLOCKS]:
        col = problem._plan.means(np.where(valid, (t >= t0).astype(float), np.nan))[:, None]
        got = proj.ssr_with(col)
        if got is not None and got < best[0]:
            best = (got, float(t0), col)
    if best[2] is None:
        return effects
    b_drift = problem.bic(effects, n_eff)
    # the others' columns and parameters are charged alike; the step pays one column and its time
    charged_others = problem.bic(others, n_eff) - n_eff * np.log(max(problem.ssr(others), 1e-300))
    b_step = n_eff * np.log(max(best[0], 1e-300)) + charged_others + 2.0 * np.log(n_eff)
    if b_step < b_drift - DBIC_MIN:
        X = np.column_stack([problem.design(others), best[2]])
        ok = problem.rows & np.all(np.isfinite(X), axis=1)
        size = float(_lstsq(X[ok], problem.yb[ok])[-1])
        steps.append({"time_drift_is_a_step": {"step_at_s": float(best[1] - t[0]), "step_dph": size,
                                               "bic_margin_over_drift": float(b_drift - b_step)}})
        return others
    return effects


def _stopped(left: float, stop_std100: float) -> dict[str, str]:
    return {"stopped": f"training residual std100 {left:.4g} is at the noise floor (<= {stop_std100:.4g})"}


def _at_floor(single, chosen, stop_at) -> bool:
    """The best single addition already brings the training residual to its noise floor: a pair
    would only fit noise."""
    if stop_at is None:
        return False
    left = float(np.nanstd(single[1].resid, ddof=1))
    return left <= stop_at(chosen + single[0])


def prune(problem: SearchProblem, effects: tuple[fx.Effect, ...],
          steps: list[dict[str, Any]]) -> tuple[fx.Effect, ...]:
    """Backward pass on TRAIN: an effect that no longer passes the gates given all the others (an
    early choice made redundant by later ones) is removed, the weakest first.  The others keep their
    families and are judged with their continuous parameters re-fitted jointly without it (a time
    constant or width bent to make room for a later effect would otherwise keep that effect looking
    necessary)."""
    current = tuple(effects)
    while len(current) > 1:
        weakest = None
        full = problem.score(current)
        for i, e in enumerate(current):
            others = problem.refit_params(current[:i] + current[i + 1:], keep_families=True)
            ev = gates(problem, problem.score(others), full, (e,), with_gls=False)
            if _redundant(ev) and (weakest is None or ev["delta_bic"] < weakest[1]):
                weakest = (i, ev["delta_bic"], others)
        if weakest is None:
            break
        steps.append({"pruned": current[weakest[0]].label, "delta_bic_given_the_others": weakest[1]})
        current = weakest[2]
    return current


def _redundant(ev: dict[str, Any]) -> bool:
    """Backward-pass verdict on one effect given all the others: redundant when the nested-model BIC
    (effective n) no longer pays for it.  Every effect passed the HAC Wald and cross-validation gates
    when it was added; given later effects those two are no judges of redundancy: two collinear
    effects (a memory and a lag bent to mimic it) inflate each other's coefficient variance, which the
    Wald test reads as weak evidence, and a transient at a segment's edge (a warm-up) is extrapolated
    from segments where its column is nearly zero, which the cross-validation reads as harm."""
    return bool(not ev["passed"] and ev["delta_bic"] <= DBIC_MIN)


def _describe(eff: fx.Effect, ev: dict[str, Any]) -> dict[str, Any]:
    return {"kind": eff.kind, "params": eff.params, "delta_bic": ev["delta_bic"], "cv_gain": ev["cv_gain"]}


def _xy(problem: SearchProblem, effects: tuple[fx.Effect, ...]) -> tuple[np.ndarray, np.ndarray]:
    X = problem.design(effects)
    return X[problem.rows], problem.yb[problem.rows]


def _cols_of(problem: SearchProblem, effects: tuple[fx.Effect, ...], j: int) -> list[int]:
    start = problem.Xb.shape[1] + sum(problem.columns(e).shape[1] for e in effects[:j])
    return list(range(start, start + problem.columns(effects[j]).shape[1]))
