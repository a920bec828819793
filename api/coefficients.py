"""Reading a gyro's coefficients (shared by ``GET /gyros/{id}/coefficients`` and ``bench coefficients``).

The answer holds, per model, the latest *accepted* version (or the requested ``version``), with each
channel's coefficients, units, probe (the temperature probe the channel's model is built on),
validity range and model definition.  One indexed query on
``fits (gyro_id, model, channel, version)``, its statement built once per request shape; the JSON columns
are decoded with orjson.  ``coefficients_etag`` names an answer by its fit rows (for ETag / 304).
"""
from __future__ import annotations

import json
from typing import Any

import orjson
from sqlalchemy import Text, bindparam, func, select, type_coerce

from bench.storage.db import Database
from bench.storage.models import Fit, Gyro
from api.views import iso


class NoCoefficients(LookupError):
    def __init__(self, message: str, gyro_known: bool) -> None:
        super().__init__(message)
        self.gyro_known = gyro_known


_COLUMNS = ("id", "model", "channel", "version", "coefficients", "result", "accepted", "created_at", "run_ids")
_JSON_COLUMNS = ("coefficients", "result", "run_ids")
_STATEMENTS: dict[tuple[bool, bool], Any] = {}


def _statement(by_model: bool, by_version: bool):
    """The query for one shape of request, built once (bound parameters ``gid``, ``model``, ``version``).
    The JSON columns come back as stored text: ``_loads`` decodes them (orjson), not the column type."""
    stmt = _STATEMENTS.get((by_model, by_version))
    if stmt is None:
        f = Fit.__table__.c
        cols = [type_coerce(f[c], Text).label(c) if c in _JSON_COLUMNS else f[c] for c in _COLUMNS]
        stmt = select(*cols).where(f.gyro_id == bindparam("gid"))
        if by_model:
            stmt = stmt.where(f.model == bindparam("model"))
        stmt = stmt.where(f.version == bindparam("version")) if by_version else stmt.where(f.accepted.is_(True))
        stmt = _STATEMENTS[(by_model, by_version)] = stmt.order_by(f.model, f.channel)
    return stmt


def _loads(value: Any) -> Any:
    """A JSON column's value: stored text decoded with orjson (Python's json for the NaN / Infinity tokens
    it writes and orjson refuses); a driver that decodes JSON itself (psycopg) hands objects already."""
    if not isinstance(value, (str, bytes)):
        return value
    try:
        return orjson.loads(value)
    except orjson.JSONDecodeError:
        return json.loads(value)


def coefficient_rows(db: Database, gyro_id: str, *, model: str | None = None, version: int | None = None) -> list:
    """The fit rows ``load_coefficients`` answers from (JSON columns still encoded); raises ``NoCoefficients``."""
    params: dict[str, Any] = {"gid": gyro_id, "model": model, "version": version}
    with db.engine.connect() as conn:
        rows = conn.execute(_statement(model is not None, version is not None),
                            {k: v for k, v in params.items() if v is not None}).all()
        known = bool(rows) or bool(conn.execute(select(func.count()).select_from(Gyro.__table__)
                                                .where(Gyro.__table__.c.gyro_id == gyro_id)).scalar())
    if not rows:
        if not known:
            raise NoCoefficients(f"no gyro {gyro_id!r} is stored", False)
        what = (f"{model or 'model'} version {version}" if version else
                (f"accepted {model} fit" if model else "accepted fit"))
        raise NoCoefficients(f"gyro {gyro_id!r} has no {what}", True)
    return rows


def coefficients_etag(rows: list) -> str:
    """A validator of the answer built from ``rows``: fit rows are never rewritten (a new fit is a new row),
    only their ``accepted`` flag changes, so their ids and flags name the document."""
    return 'W/"' + "-".join(f"{r.id}{'a' if r.accepted else 'v'}" for r in rows) + '"'


def coefficients_document(gyro_id: str, rows: list) -> dict[str, Any]:
    models: dict[str, dict[str, Any]] = {}
    for r in rows:
        m = models.setdefault(r.model, {"model": r.model, "version": r.version, "fit_id": r.id,
                                        "accepted": r.accepted, "created_at": iso(r.created_at),
                                        "run_ids": _loads(r.run_ids), "channels": {}})
        m["fit_id"] = min(m["fit_id"], r.id)
        res = _loads(r.result) or {}
        m["channels"][r.channel] = {"coefficients": _loads(r.coefficients), "units": res.get("units"),
                                    "probe": (res.get("definition") or {}).get("probe"),
                                    "validity": res.get("validity"), "definition": res.get("definition")}
    return {"gyro_id": gyro_id, "models": list(models.values())}


def load_coefficients(db: Database, gyro_id: str, *, model: str | None = None,
                      version: int | None = None) -> dict[str, Any]:
    """The latest accepted fit of each model (or of ``model``); with ``version``: that version, accepted or
    not, of ``model`` (or of every model that has it)."""
    return coefficients_document(gyro_id, coefficient_rows(db, gyro_id, model=model, version=version))


def load_fit_results(db: Database, gyro_id: str, model: str, *, version: int | None = None):
    """The ``FitResult`` of each channel of one model's accepted version (or ``version``), and a label
    naming gyro, model, version and runs.  Raises ``NoCoefficients`` like ``load_coefficients``."""
    from bench.fit.base import FitResult

    doc = load_coefficients(db, gyro_id, model=model, version=version)
    m = doc["models"][0]
    f = Fit.__table__.c
    stmt = (select(f.channel, f.result).where(f.gyro_id == gyro_id, f.model == model, f.version == m["version"])
            .order_by(f.channel))
    with db.engine.connect() as conn:
        rows = conn.execute(stmt).all()
    fields = ("model", "channel", "target", "definition", "coefficients", "units", "validity", "stats")
    results = [FitResult(**{k: (r.result or {})[k] for k in fields if k in (r.result or {})}) for r in rows]
    label = (f"model {model} version {m['version']}{' (accepted)' if m['accepted'] else ''}, "
             f"runs {', '.join(str(x) for x in m['run_ids'] or [])}")
    return results, label


def export_coefficients(db: Database, gyro_id: str, model: str, fmt: str, *, version: int | None = None,
                        options: dict[str, Any] | None = None) -> tuple[str, str, str]:
    """(text, media type, file suffix) of a gyro's model in ``fmt`` (``bench.fit.firmware.FORMATS``).
    Raises ``NoCoefficients`` or ``bench.fit.firmware.NotExpressible`` (with the reason)."""
    from bench.fit.firmware import FORMATS, NotExpressible, render

    if fmt not in FORMATS:
        raise NotExpressible(f"unknown format {fmt!r} (use one of {', '.join(FORMATS)})")
    results, label = load_fit_results(db, gyro_id, model, version=version)
    return render(fmt, gyro_id, results, label=label, options=options)
