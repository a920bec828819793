"""Shared types of the fitting module.  Pure data; no I/O.

A *dataset* is a ``Dataset``: named 1-D float arrays of equal length (``time_s``, ``gyro_x``,
``temp_t1``, ``freq_x``, ``orientation`` (array of str), ...) plus metadata from the CSV header
(text values, except ``meta["channel_probes"]``: a dict channel -> the name of that channel's own
temperature probe, e.g. ``{"x": "t1", "y": "t2", "z": "t3"}``; CSV line ``# channel_probes: x=t1,y=t2,z=t3``).

``channel_probe(ds, channel)`` is the one answer to "which probe is this channel's own": the map's
probe, else the channel's name when it is also a probe name, else the first probe.

Every model fit returns a ``FitResult``; ``bench.fit.catalog.predict(result, dataset)`` evaluates it
on new data and returns the predicted bias and a boolean ``flagged`` array (outside the validity
range: clipped or refused, never silently extrapolated).
"""
from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from typing import Any


from bench.dataset import Dataset  # noqa: F401  (re-exported: the fitting module's input)
from bench.errors import DataFormatError
from bench.jsonsafe import jsonable
from bench.signal.geometry import EARTH_RATE_DPH  # noqa: F401  (re-exported; defined in bench.signal)


_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")


def parse_channel_probes(text: str) -> dict[str, str]:
    """``"x=t1,y=t2,z=t3"`` -> ``{"x": "t1", "y": "t2", "z": "t3"}``; ValueError naming the bad part."""
    out: dict[str, str] = {}
    for part in str(text).split(","):
        item = part.strip()
        if not item:
            raise ValueError(f"channel_probes {text!r}: empty item (write channel=probe pairs joined by ',')")
        ch, sep, probe = (s.strip() for s in item.partition("="))
        if not sep or not _NAME_RE.match(ch) or not _NAME_RE.match(probe):
            raise ValueError(f"channel_probes {text!r}: cannot read {item!r} (write channel=probe, names of "
                             f"letters, digits or _)")
        if ch in out:
            raise ValueError(f"channel_probes {text!r}: channel {ch!r} given twice")
        out[ch] = probe
    return out


def format_channel_probes(mapping: dict[str, str]) -> str:
    """``{"x": "t1", "y": "t2"}`` -> ``"x=t1,y=t2"`` (the CSV metadata form; round-trips with the parser)."""
    text = ",".join(f"{ch}={probe}" for ch, probe in mapping.items())
    parse_channel_probes(text)
    return text


DEFAULT_PROBE = "t1"      # S000/S001: probe T1 is the model temperature unless a map or a fit names another


def default_probe(ds: Dataset, channel: str) -> str:
    """The probe a channel uses when no map says otherwise: a probe named like the channel, else
    ``t1``; never another probe in its place (a missing T1 is an error naming it)."""
    names = ds.temp_names()
    if channel in names:
        return channel
    if DEFAULT_PROBE in names:
        return DEFAULT_PROBE
    raise DataFormatError(f"no temp_{DEFAULT_PROBE} (the default probe) in data; give probe=NAME or a "
                          f"channel_probes map to use another (temperature columns: "
                          f"{', '.join(f'temp_{n}' for n in names) or 'none'})", column=f"temp_{DEFAULT_PROBE}")


def channel_probe_map(ds: Dataset) -> dict[str, str]:
    """The data's channel -> own-probe map (empty when none is declared).  ``meta["channel_probes"]``
    may hold the dict (CSV reader, run export) or its text form ``"x=t1,y=t2"`` (a dataset built in
    memory); a malformed text is a ``DataFormatError`` naming it."""
    raw = ds.meta.get("channel_probes")
    if not raw:
        return {}
    if isinstance(raw, dict):
        return {str(ch): str(probe) for ch, probe in raw.items()}
    try:
        return parse_channel_probes(str(raw))
    except ValueError as exc:
        raise DataFormatError(f"metadata {exc}") from None


def channel_probe(ds: Dataset, channel: str) -> str:
    """The channel's own temperature probe: ``ds.meta["channel_probes"][channel]`` when the data
    declares it (bench config / run metadata / CSV ``# channel_probes:`` line), else
    ``default_probe``.  A mapped probe without a ``temp_<probe>`` column is an error."""
    mapping = channel_probe_map(ds)
    if channel not in mapping:
        return default_probe(ds, channel)
    probe = mapping[channel]
    if f"temp_{probe}" not in ds:
        raise DataFormatError(f"channel {channel!r}: its probe {probe!r} (metadata channel_probes "
                              f"{format_channel_probes(mapping)}) has no column temp_{probe} in the data "
                              f"(probes: {', '.join(ds.temp_names()) or 'none'})", column=f"temp_{probe}")
    return probe


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
