"""Run segments and segment-aware block means.

A *segment* is a contiguous piece of a record (a ``slice`` of sample indices) that blocks, filters and
rates never cross: a new run, a new orientation, a jump back in time or a long gap starts a new one.

Block means (the "100-s means" of bias stability, S000 Table 3, and the 100-s smoothing of S004):
inside each segment, samples are grouped into consecutive blocks of ``block_s`` seconds aligned on the
segment's first sample (so a block never mixes two runs or two positions).  Non-finite values are
ignored per column (a block whose values are all missing gives NaN).  A block holding fewer than
``min_fraction`` x the median block sample count of its segment (a ragged end) is dropped.  When the
data are already at (or coarser than) the block spacing (median step >= 0.9 ``block_s``) every sample
is its own block.
"""
from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np


def run_segments(time_s: np.ndarray, run: np.ndarray | None = None, gap_factor: float = 5.0) -> list[slice]:
    """Contiguous pieces of a record: split where time (s) does not increase, where a gap exceeds
    ``gap_factor`` x the median positive sample step (``math.inf``: never split on gaps), or where
    the ``run`` label (any array of labels, e.g. run ids or orientation codes) changes."""
    t = np.asarray(time_s, float)
    n = t.size
    if n == 0:
        return []
    if n == 1:
        return [slice(0, 1)]
    dt = np.diff(t)
    positive = dt[dt > 0]
    step = float(np.median(positive)) if positive.size else 1.0
    cut = (dt <= 0) | (dt > gap_factor * step)
    if run is not None:
        r = np.asarray(run)
        cut |= r[1:] != r[:-1]
    edges = np.concatenate([[0], np.nonzero(cut)[0] + 1, [n]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


class BlockMeans(NamedTuple):
    """Result of ``block_means``: mean time (s) of each kept block, the averaged columns, the segments
    of the averaged series, and the index of the first sample of each kept block in the input."""

    time_s: np.ndarray
    columns: dict[str, np.ndarray]
    segments: list[slice]
    first_index: np.ndarray


class BlockPlan:
    """Which block every sample of a time axis falls in (the rules of ``block_means``), computed once:
    averaging many columns on the same axis then costs one weighted count each."""

    def __init__(self, time_s: np.ndarray, block_s: float, segments: list[slice] | None = None, *,
                 min_fraction: float = 0.5) -> None:
        t = np.asarray(time_s, float)
        if segments is None:
            segments = [slice(0, t.size)] if t.size else []
        block_of = np.full(t.size, -1, dtype=np.int64)   # global block number of each sample, -1 = unused
        kept_blocks: list[np.ndarray] = []
        out_segments: list[slice] = []
        next_block = 0
        pos = 0
        for seg in segments:
            ts = t[seg]
            if ts.size == 0:
                continue
            step = float(np.median(np.diff(ts))) if ts.size > 1 else block_s
            if block_s <= 0 or step >= 0.9 * block_s:          # already at (or coarser than) block spacing
                ids = np.arange(ts.size)
            else:
                ids = np.floor((ts - ts[0]) / block_s).astype(np.int64)
            uniq, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
            keep = counts >= min_fraction * np.median(counts)
            block_of[seg] = next_block + inverse
            kept_blocks.append(next_block + np.flatnonzero(keep))
            next_block += uniq.size
            m = int(keep.sum())
            if m:
                out_segments.append(slice(pos, pos + m))
                pos += m
        self.kept = np.concatenate(kept_blocks) if kept_blocks else np.zeros(0, dtype=np.int64)
        self.used = block_of >= 0
        self.ids_used = block_of[self.used]
        self.n_blocks = next_block
        self.segments = out_segments
        first = np.full(next_block, -1, dtype=np.int64)
        idx_used = np.flatnonzero(self.used)
        first[self.ids_used[::-1]] = idx_used[::-1]                    # first sample of every block
        self.first_index = first[self.kept]
        self._every_sample_used = bool(self.used.all())
        self._counts: np.ndarray | None = None
        self.time_s = self.means(t)

    def means(self, values: np.ndarray) -> np.ndarray:
        """Mean of ``values`` (one per sample of the axis) over every kept block, NaN ignored."""
        v = np.asarray(values, float)
        if not self._every_sample_used:
            v = v[self.used]
        if np.isfinite(v).all():       # the common case: the samples per block, counted once
            if self._counts is None:
                self._counts = np.bincount(self.ids_used, minlength=self.n_blocks).astype(float)
            n, s = self._counts, np.bincount(self.ids_used, weights=v, minlength=self.n_blocks)
        else:
            ok = np.isfinite(v)
            n = np.bincount(self.ids_used, weights=ok.astype(float), minlength=self.n_blocks)
            s = np.bincount(self.ids_used, weights=np.where(ok, v, 0.0), minlength=self.n_blocks)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, s / np.maximum(n, 1), np.nan)[self.kept]


def block_means(time_s: np.ndarray, columns: Mapping[str, np.ndarray], block_s: float,
                segments: list[slice] | None = None, *, min_fraction: float = 0.5) -> BlockMeans:
    """Mean of every column over consecutive ``block_s``-second blocks inside each segment (see the
    module docstring for the rules).  ``segments`` defaults to the whole record as one segment.
    Unpacks as ``(time_s, columns, segments, first_index)``."""
    plan = BlockPlan(time_s, block_s, segments, min_fraction=min_fraction)
    return BlockMeans(plan.time_s, {k: plan.means(v) for k, v in columns.items()}, plan.segments, plan.first_index)
