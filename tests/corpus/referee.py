"""The referee: score the product's close-the-loop report on a corpus case against the truth.

Per channel under test:

* kinds and probes: the (kind, probes) the product added match the true effects one to one
  (read through ``added_effects``, the one adapter to the report's schema); a look-alike that the
  data cannot tell from the true effect (under half a noise floor apart, see the generator) counts
  as right; for a complete model nothing may be added; for an effect no column records, kinds are
  not scored;
* verdict: one of the truth's honest verdicts;
* error: the "after" validation std of 100-s means within ``ORACLE_TOLERANCE`` x that of the oracle
  (declared terms + the true effects in their true form, least squares on TRAIN), and never above
  "before" (the declared model alone).  Both are computed here from the data, on the validation
  samples where every declared-model temperature lies inside the TRAIN range (also on all samples,
  reported); "after" is recomputed from the product's validation residual.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import permutations
from typing import Any

import numpy as np

from bench.fit.base import Dataset
from tests.corpus.cases import Case, ChannelTruth
from tests.corpus.generator import declared_columns
from tests.corpus.physics import earth_rate_body

ORACLE_TOLERANCE = 1.15
LOST_INFORMATION_FLOORS = 1.5       # oracle above this many noise floors: "partly_explained" is honest too
NOT_WORSE_TOLERANCE = 1e-6          # relative; rounding between the product's before and ours
BLOCK_S = 100.0


# ------------------------------------------------------------------------------- report adapter

PROBE_FREE_KINDS = frozenset({"warmup", "g_sensitivity", "time_drift"})


def _kind_name(kind: str) -> str:
    # a gradual (memory) hysteresis may get its own kind name beside the relay; both are hysteresis
    return "hysteresis" if "hysteresis" in kind else kind


def _probe_set(params: dict[str, Any]) -> frozenset[str]:
    value = params.get("probes", params.get("probe"))
    if value is None:
        return frozenset()
    if isinstance(value, str):
        return frozenset(p for p in value.replace(",", "-").split("-") if p)
    return frozenset(str(p) for p in value)


def added_effects(channel_report: dict[str, Any]) -> list[tuple[str, frozenset[str]]]:
    """(kind, probes) of every effect the product added: the ONE place that reads the report's
    effect schema (effects_added[i]["kind"], effects_added[i]["params"]["probe" | "probes"])."""
    out = []
    for e in channel_report.get("effects_added", []):
        kind = _kind_name(e["kind"])
        out.append((kind, frozenset() if kind in PROBE_FREE_KINDS else _probe_set(e.get("params", {}))))
    return out


def product_validation_residual(channel_report: dict[str, Any], n_validate: int) -> np.ndarray | None:
    """The product's "after" residual on the whole validation run, when the report carries it."""
    res = channel_report.get("_residuals", {}).get("after")
    if res is None:
        return None
    r = np.asarray(res[1], dtype=float)
    return r if len(r) == n_validate else None


# ------------------------------------------------------------------------------- numbers

def std100(residual: np.ndarray, time_s: np.ndarray, keep: np.ndarray | None = None) -> float:
    """Std (ddof=1) of 100-s means over consecutive blocks of time from the run's start (a logger
    outage leaves its blocks out); a block counts when its span has ended within the run and at least half
    the samples it should hold are there; with ``keep``, only blocks whose samples are all kept; samples with a missing value are
    left out of their block."""
    t = np.asarray(time_s, dtype=float)
    dt = float(np.median(np.diff(t)))
    per = max(1, int(round(BLOCK_S / dt)))
    block = np.floor((t - t[0] + dt / 2) / BLOCK_S).astype(np.int64)
    r = np.asarray(residual, dtype=float)
    ok = np.isfinite(r)
    nb = int(block.max()) + 1
    cnt = np.bincount(block, ok.astype(float), nb)
    tot = np.bincount(block, np.where(ok, r, 0.0), nb)
    use = (cnt >= per // 2) & (np.arange(nb) < np.floor((t[-1] - t[0] + dt) / BLOCK_S + 1e-9))  # no ragged end
    if keep is not None:
        use &= np.bincount(block, (~np.asarray(keep, dtype=bool)).astype(float), nb) == 0
    means = tot[use] / cnt[use]
    return float(np.std(means, ddof=1)) if len(means) >= 2 else float("nan")


def target(ds: Dataset, channel: str) -> np.ndarray:
    """gyro_<channel> with the known inputs removed: Earth rate along the axis and the table rate."""
    orient = np.asarray(ds["orientation"], dtype=object) if "orientation" in ds else np.full(len(ds), "NUE", dtype=object)
    y = np.asarray(ds[f"gyro_{channel}"], dtype=float) - earth_rate_body(orient, float(ds.meta["latitude_deg"]))[:, "xyz".index(channel)]
    if "table_rate_dps" in ds:
        y = y - np.nan_to_num(np.asarray(ds["table_rate_dps"], dtype=float)) * 3600.0
    return y


def declared_design(truth: ChannelTruth, ds: Dataset) -> np.ndarray:
    X = declared_columns(truth.declared, lambda p: np.asarray(ds[f"temp_{p}"], dtype=float))
    return np.column_stack([np.ones(len(ds)), X])


def in_range(truth: ChannelTruth, train: Dataset, validate: Dataset) -> np.ndarray:
    keep = np.ones(len(validate), dtype=bool)
    for p in truth.declared_probes:
        lo, hi = np.nanmin(train[f"temp_{p}"]), np.nanmax(train[f"temp_{p}"])
        v = np.asarray(validate[f"temp_{p}"], dtype=float)
        keep &= (v >= lo) & (v <= hi)
    return keep


def fit_and_validate(X_tr: np.ndarray, y_tr: np.ndarray, X_va: np.ndarray) -> np.ndarray:
    ok = np.all(np.isfinite(X_tr), axis=1) & np.isfinite(y_tr)
    scale = np.sqrt(np.mean(X_tr[ok] ** 2, axis=0))
    scale[scale == 0] = 1.0
    beta, *_ = np.linalg.lstsq(X_tr[ok] / scale, y_tr[ok], rcond=None)
    return X_va @ (beta / scale)


@dataclass
class Reference:
    """Before (declared model) and oracle (declared + true effects) validation errors, in range and on
    all samples, plus the validation coverage."""

    before_in: float
    before_all: float
    oracle_in: float
    oracle_all: float
    coverage: float
    keep: np.ndarray = field(repr=False)
    residual_before: np.ndarray = field(repr=False)
    residual_oracle: np.ndarray = field(repr=False)


def reference(case: Case, channel: str) -> Reference:
    truth = case.truth[channel]
    tr, va = case.train, case.validate
    y_tr, y_va = target(tr, channel), target(va, channel)
    D_tr, D_va = declared_design(truth, tr), declared_design(truth, va)
    r_before = y_va - fit_and_validate(D_tr, y_tr, D_va)
    O_tr = np.column_stack([D_tr, case.oracle_columns(channel, "train")])
    O_va = np.column_stack([D_va, case.oracle_columns(channel, "validate")])
    r_oracle = y_va - fit_and_validate(O_tr, y_tr, O_va)
    keep = in_range(truth, tr, va)
    t = va.time
    return Reference(std100(r_before, t, keep), std100(r_before, t), std100(r_oracle, t, keep),
                     std100(r_oracle, t), float(np.mean(keep)), keep, r_before, r_oracle)


# ------------------------------------------------------------------------------- scoring

@dataclass
class ChannelScore:
    case_class: str
    seed: int
    channel: str
    passed: bool
    reasons: list[str]
    numbers: dict[str, Any]


def score_channel(case: Case, channel: str, channel_report: dict[str, Any]) -> ChannelScore:
    truth = case.truth[channel]
    ref = reference(case, channel)
    reasons: list[str] = []
    got = added_effects(channel_report)
    want = [(e.kind, frozenset(e.probes)) for e in truth.effects if e.explainable]
    explainable = all(e.explainable for e in truth.effects)
    if explainable and not kinds_match(got, truth):
        reasons.append("kinds: got " + _fmt(got) + ", want " + _fmt(want))
    verdict = channel_report.get("verdict")
    honest = set(truth.verdicts)
    if "explained" in honest and ref.oracle_in > LOST_INFORMATION_FLOORS * case.floors[channel]:
        # the true effects in their true form, from the recorded data, stay well above the noise floor
        # (e.g. a power-on inside a logger outage): structure is left that no analysis can remove
        honest.add("partly_explained")
    if verdict not in honest:
        reasons.append(f"verdict: got {verdict}, want {'|'.join(sorted(honest))}")
    resid = product_validation_residual(channel_report, len(case.validate))
    if resid is not None:
        after_in = std100(resid, case.validate.time, ref.keep)
        after_all = std100(resid, case.validate.time)
        source = "residual"
    else:
        after_in = float(channel_report["after"]["validation_std100_dph"])
        after_all = float(channel_report["after"].get("validation_all_std100_dph", float("nan")))
        source = "report"
    if not after_in <= ref.before_in * (1 + NOT_WORSE_TOLERANCE):
        reasons.append(f"worse: after {after_in:.4g} > before {ref.before_in:.4g}")
    if explainable and not after_in <= ORACLE_TOLERANCE * ref.oracle_in:
        reasons.append(f"error: after {after_in:.4g} = {after_in / ref.oracle_in:.2f}x oracle {ref.oracle_in:.4g}")
    numbers = {"after_in": after_in, "after_all": after_all, "before_in": ref.before_in, "before_all": ref.before_all,
               "oracle_in": ref.oracle_in, "oracle_all": ref.oracle_all, "coverage": ref.coverage,
               "noise_floor_truth": case.floors[channel], "after_source": source, "verdict": verdict,
               "added": _fmt(got), "truth": _fmt(want + [(e.kind, frozenset(e.probes)) for e in truth.effects
                                                          if not e.explainable])}
    return ChannelScore(case.case_class, case.seed, channel, not reasons, reasons, numbers)


def kinds_match(got: list[tuple[str, frozenset[str]]], truth: ChannelTruth) -> bool:
    """One added effect per true effect, each the true (kind, probes) or one of its look-alikes
    (regressors the data cannot tell from it; probes ignored for probe-free kinds)."""
    accept = []
    for e, look in zip(truth.effects, truth.lookalikes):
        names = {(e.kind, frozenset(e.probes))} | {(k, frozenset(p)) for k, p in look}
        accept.append({(k, frozenset() if k in PROBE_FREE_KINDS else p) for k, p in names})
    if len(got) != len(accept):
        return False
    return any(all(g in accept[j] for g, j in zip(got, perm)) for perm in permutations(range(len(accept))))


def _fmt(effects: list[tuple[str, frozenset[str]]]) -> str:
    if not effects:
        return "[]"
    return "[" + ", ".join(k + ("(" + "-".join(sorted(p)) + ")" if p else "") for k, p in effects) + "]"


def run_product(case: Case, channel: str) -> dict[str, Any]:
    """Run the product's close-the-loop on the case for one channel with its declared formula."""
    from bench.fit.closeloop import close_loop

    train, validate = case.product_runs
    report = close_loop(train, validate, case.truth[channel].formula, channels=[channel])
    return report["channels"][channel]


def score_case(case: Case) -> list[ChannelScore]:
    out = []
    for ch in case.truth:
        try:
            report = run_product(case, ch)
        except Exception as exc:  # the product failing on a case is a failed case, named
            out.append(ChannelScore(case.case_class, case.seed, ch, False,
                                    [f"crash: {type(exc).__name__}: {exc}"[:300]], {}))
            continue
        out.append(score_channel(case, ch, report))
    return out
