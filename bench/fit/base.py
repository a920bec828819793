"""Shared types of the fitting module.  Pure data; no I/O.

A *dataset* is a ``Dataset``: named 1-D float arrays of equal length (``time_s``, ``gyro_x``,
``temp_t1``, ``freq_x``, ``orientation`` (array of str), ...) plus metadata from the CSV header.

Every model fit returns a ``FitResult``; ``bench.fit.catalog.predict(result, dataset)`` evaluates it
on new data and returns the predicted bias and a boolean ``flagged`` array (outside the validity
range: clipped or refused, never silently extrapolated).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from bench.jsonsafe import jsonable
from bench.signal.geometry import EARTH_RATE_DPH  # noqa: F401  (re-exported; defined in bench.signal)


@dataclass
class Dataset:
    columns: dict[str, np.ndarray]
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["time_s"]) if "time_s" in self.columns else 0

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.columns[name]
        except KeyError:
            raise KeyError(f"column {name!r} not in data (have: {', '.join(sorted(self.columns))})") from None

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    @property
    def time(self) -> np.ndarray:
        return self.columns["time_s"]

    def gyro_channels(self) -> list[str]:
        return [c[len("gyro_"):] for c in self.columns if c.startswith("gyro_")]

    def temp_names(self) -> list[str]:
        return [c[len("temp_"):] for c in self.columns if c.startswith("temp_")]

    def select(self, mask: np.ndarray) -> "Dataset":
        return Dataset({k: v[mask] for k, v in self.columns.items()}, dict(self.meta))

    def with_columns(self, **cols: np.ndarray) -> "Dataset":
        merged = dict(self.columns)
        merged.update(cols)
        return Dataset(merged, dict(self.meta))


@dataclass
class FitResult:
    """One fitted model for one channel.

    ``model``: registry name ("static", "dynamic", "patent37", "hrg", "hrg_pso", "hrg_reverse",
    "fog_stepwise", "fog_delaunay", or "formula").  ``definition``: everything needed to evaluate the
    model without this code (formula text, term list, reference temperature, probe names, filter
    settings).  ``coefficients``: term name -> value; ``units``: term name -> unit text.
    ``validity``: {"tmin_c", "tmax_c", ...; "hull": [[T, dTdt], ...] where it applies}.
    ``stats``: fit statistics (rms_dph, std100_dph, n, r2, cond, ...).
    """

    model: str
    channel: str
    target: str                       # e.g. "gyro_x" (deg/h) or "temp_t2" for hrg_reverse
    definition: dict[str, Any]
    coefficients: dict[str, float]
    units: dict[str, str]
    validity: dict[str, Any]
    stats: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return jsonable(asdict(self))
