"""Procedures (parameter schema and defaults), benches (devices and live status) and health."""
from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request, Response
from sqlalchemy import select, text

import procedures
from api.auth import Principal, require
from api.deps import get_db, stale_after_s
from api.problems import Problem, problem_codes
from api.schemas import ID_PATTERN, ProcedureName
from api.views import bench_doc
from bench.storage.db import Database
from bench.storage.models import Bench

router = APIRouter()


def _procedure_doc(name: str) -> dict[str, Any]:
    module = procedures.get(name)
    return {"name": module.NAME, "description": module.DESCRIPTION,
            "parameters_schema": module.Params.model_json_schema(),
            "defaults": module.Params().model_dump(mode="json")}


@router.get("/procedures", tags=["procedures"], summary="Procedures with their parameter schema and defaults")
def list_procedures(_: Principal = Depends(require("viewer"))) -> dict[str, Any]:
    return {"procedures": [_procedure_doc(n) for n in procedures.PROCEDURE_MODULES]}


@router.get("/procedures/{name}", tags=["procedures"], summary="One procedure")
def get_procedure(name: ProcedureName, _: Principal = Depends(require("viewer"))) -> dict[str, Any]:
    if name not in procedures.PROCEDURE_MODULES:
        raise Problem(404, "Unknown procedure", f"procedure {name!r} does not exist; known: "
                      f"{', '.join(procedures.PROCEDURE_MODULES)}")
    return _procedure_doc(name)


@router.get("/benches", tags=["benches"], summary="Benches: devices, worker presence, current run, queue")
def list_benches(request: Request, db: Database = Depends(get_db),
                 _: Principal = Depends(require("viewer"))) -> dict[str, Any]:
    with db.session() as s:
        return {"benches": [bench_doc(s, b, stale_after_s(request))
                            for b in s.scalars(select(Bench).order_by(Bench.name))]}


@router.get("/benches/{name}", tags=["benches"], summary="One bench")
def get_bench(name: Annotated[str, Path(pattern=ID_PATTERN)], request: Request, db: Database = Depends(get_db),
              _: Principal = Depends(require("viewer"))) -> dict[str, Any]:
    with db.session() as s:
        bench = s.scalars(select(Bench).where(Bench.name == name)).first()
        if bench is None:
            raise Problem(404, "Unknown bench", f"bench {name!r} is not configured")
        return bench_doc(s, bench, stale_after_s(request))


@router.get("/health", tags=["health"], summary="Liveness and database reachability (no token needed)",
            openapi_extra=problem_codes(503))
def health(db: Database = Depends(get_db)) -> dict[str, Any]:
    try:
        with db.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # noqa: BLE001 - health reports the failure instead of raising
        raise Problem(503, "Database unavailable", f"{type(exc).__name__}: {str(exc).splitlines()[0]}") from None
    return {"status": "ok", "database": db.dialect}


@router.get("/metrics", tags=["health"], summary="Prometheus metrics (text exposition format, bench_ prefix)",
            response_class=Response, responses={200: {"content": {"text/plain": {}}}})
def metrics(request: Request, _: Principal = Depends(require("viewer"))) -> Response:
    from bench.metrics import exposition

    body, content_type = exposition(request.app.state.metrics_registry)
    return Response(body, media_type=content_type)
