"""Reading a gyro's coefficients (shared by ``GET /gyros/{id}/coefficients`` and ``bench coefficients``).

The answer holds, per model, the latest *accepted* version (or the requested ``version``), with each
channel's coefficients, units, probe (the temperature probe the channel's model is built on),
validity range and model definition.  One indexed query on
``fits (gyro_id, model, channel, version)``.
"""
from __future__ import annotations

from typing import Any

from sqlalchemy import func, select

from bench.storage.db import Database
from bench.storage.models import Fit, Gyro
from api.views import iso


class NoCoefficients(LookupError):
    def __init__(self, message: str, gyro_known: bool) -> None:
        super().__init__(message)
        self.gyro_known = gyro_known


def load_coefficients(db: Database, gyro_id: str, *, model: str | None = None,
                      version: int | None = None) -> dict[str, Any]:
    """The latest accepted fit of each model (or of ``model``); with ``version``: that version, accepted or
    not, of ``model`` (or of every model that has it)."""
    f = Fit.__table__.c
    stmt = select(f.id, f.model, f.channel, f.version, f.coefficients, f.result, f.accepted, f.created_at,
                  f.run_ids).where(f.gyro_id == gyro_id)
    if model is not None:
        stmt = stmt.where(f.model == model)
    stmt = stmt.where(f.version == version) if version is not None else stmt.where(f.accepted.is_(True))
    with db.engine.connect() as conn:
        rows = conn.execute(stmt.order_by(f.model, f.channel)).all()
        known = bool(rows) or bool(conn.execute(select(func.count()).select_from(Gyro.__table__)
                                                .where(Gyro.__table__.c.gyro_id == gyro_id)).scalar())
    if not rows:
        if not known:
            raise NoCoefficients(f"no gyro {gyro_id!r} is stored", False)
        what = (f"{model or 'model'} version {version}" if version else
                (f"accepted {model} fit" if model else "accepted fit"))
        raise NoCoefficients(f"gyro {gyro_id!r} has no {what}", True)
    models: dict[str, dict[str, Any]] = {}
    for r in rows:
        m = models.setdefault(r.model, {"model": r.model, "version": r.version, "fit_id": r.id,
                                        "accepted": r.accepted, "created_at": iso(r.created_at),
                                        "run_ids": r.run_ids, "channels": {}})
        m["fit_id"] = min(m["fit_id"], r.id)
        res = r.result or {}
        m["channels"][r.channel] = {"coefficients": r.coefficients, "units": res.get("units"),
                                    "probe": (res.get("definition") or {}).get("probe"),
                                    "validity": res.get("validity"), "definition": res.get("definition")}
    return {"gyro_id": gyro_id, "models": list(models.values())}


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
