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


from bench.dataset import Dataset  # noqa: F401  (re-exported: the fitting module's input)
from bench.jsonsafe import jsonable
from bench.signal.geometry import EARTH_RATE_DPH  # noqa: F401  (re-exported; defined in bench.signal)


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
