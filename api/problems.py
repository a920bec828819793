"""Errors as RFC 9457 problem details (``application/problem+json``) with messages a person
understands: what was wrong and where.  The package's typed errors map to status codes here."""
from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from bench.errors import BenchError, DataFormatError, PlanError
from bench.storage.errors import InvalidTransition, StorageUnavailable, UnknownRun

log = logging.getLogger(__name__)
MEDIA_TYPE = "application/problem+json"
_TITLES = {400: "Bad request", 401: "Authentication required", 403: "Not allowed", 404: "Not found",
           405: "Method not allowed", 406: "Not acceptable", 409: "Conflict", 413: "Too large",
           415: "Unsupported media type", 422: "Invalid input", 500: "Internal error", 503: "Unavailable"}


class Problem(Exception):
    """Raise from an endpoint to answer with a problem document."""

    def __init__(self, status: int, title: str, detail: str, *, headers: dict[str, str] | None = None,
                 **extra: Any) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail, self.headers, self.extra = status, title, detail, headers, extra


def problem_response(request: Request, status: int, title: str, detail: str, headers: dict[str, str] | None = None,
                     **extra: Any) -> JSONResponse:
    body = {"type": "about:blank", "title": title, "status": status, "detail": detail,
            "instance": request.url.path, **extra}
    return JSONResponse(body, status_code=status, media_type=MEDIA_TYPE, headers=headers)


def _where(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc)


def validation_errors(errors: list[dict[str, Any]], prefix: tuple[Any, ...] = ()) -> list[dict[str, str]]:
    out = []
    for e in errors:
        msg = e.get("msg", "invalid")
        if e.get("type") == "extra_forbidden":
            msg = "unknown field (not accepted here)"
        elif e.get("type") == "missing":
            msg = "required field missing"
        out.append({"where": _where(prefix + tuple(e.get("loc", ()))), "problem": msg})
    return out


def summary(errors: list[dict[str, str]]) -> str:
    first = "; ".join(f"{e['where']}: {e['problem']}" for e in errors[:5])
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return first + more


def install(app: FastAPI) -> None:
    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        return problem_response(request, exc.status, exc.title, exc.detail, exc.headers, **exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        errors = validation_errors(list(exc.errors()))
        return problem_response(request, 422, "Invalid input", summary(errors), errors=errors)

    @app.exception_handler(ValidationError)
    async def _invalid_model(request: Request, exc: ValidationError):
        errors = validation_errors(list(exc.errors()))
        return problem_response(request, 422, "Invalid input", summary(errors), errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no such resource: {request.method} {request.url.path}"
        return problem_response(request, exc.status_code, _TITLES.get(exc.status_code, "Error"), detail,
                                getattr(exc, "headers", None))

    @app.exception_handler(BenchError)
    async def _bench(request: Request, exc: BenchError):
        if isinstance(exc, UnknownRun):
            return problem_response(request, 404, "Not found", str(exc))
        if isinstance(exc, InvalidTransition):
            return problem_response(request, 409, "Conflict", str(exc))
        if isinstance(exc, StorageUnavailable):
            return problem_response(request, 503, "Database unavailable", str(exc), {"Retry-After": "5"})
        if isinstance(exc, (PlanError, DataFormatError)):
            return problem_response(request, 422, "Invalid input", str(exc))
        return problem_response(request, 422, "Cannot do that", f"{type(exc).__name__}: {exc}")

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        log.exception("internal error on %s %s", request.method, request.url.path)
        return problem_response(request, 500, "Internal error",
                                f"the server failed on this request ({type(exc).__name__}); it is logged")


# ------------------------------------------------------------------------------ OpenAPI documentation
PROBLEM_SCHEMA = {
    "type": "object", "title": "Problem", "required": ["type", "title", "status", "detail", "instance"],
    "description": "RFC 9457 problem details: what was wrong and where",
    "properties": {
        "type": {"type": "string"}, "title": {"type": "string"}, "status": {"type": "integer"},
        "detail": {"type": "string"}, "instance": {"type": "string"},
        "errors": {"type": "array", "description": "one entry per invalid input",
                   "items": {"type": "object", "required": ["where", "problem"],
                             "properties": {"where": {"type": "string"}, "problem": {"type": "string"}}}},
    },
    "additionalProperties": True,
}
PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}
_DESCRIPTIONS = {400: "The body is not valid JSON", 401: "No token, or an unknown token",
                 403: "The token's role is not enough",
                 404: "No such resource", 405: "Method not allowed", 409: "Not possible in the resource's current "
                 "state", 413: "Too much data selected", 422: "Invalid input: which field and why",
                 503: "Database unavailable (retry later)"}


async def reject_unknown_query(request: Request) -> None:
    """App-wide dependency: a query parameter the route does not declare is refused (422 naming it and
    the ones the route takes) instead of being silently ignored.  Pages outside the API document (the
    dashboard's) are left alone: their query strings belong to the page's script."""
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None or not request.query_params or not getattr(route, "include_in_schema", True):
        return
    known = _query_names(dependant)
    unknown = sorted(set(request.query_params) - known)
    if unknown:
        raise Problem(422, "Invalid input", f"unknown query parameter(s) {', '.join(unknown)}; this request "
                      f"takes: {', '.join(sorted(known)) or 'none'}")


def _query_names(dependant) -> set[str]:
    """Names of the query parameters a route takes, its dependencies' included."""
    names = {p.alias for p in dependant.query_params}
    for d in dependant.dependencies:
        names |= _query_names(d)
    return names


def problem_codes(*codes: int) -> dict[str, Any]:
    """``openapi_extra`` of a route that answers these problem codes besides the ones found from its
    signature (see ``document_problems``)."""
    return {"x-problem-codes": list(codes)}


def _dependency_calls(dependant) -> list[Any]:
    out = []
    for d in dependant.dependencies:
        out.append(d.call)
        out.extend(_dependency_calls(d))
    return out


def _route_codes(route) -> set[int]:
    """Problem codes a route answers, from its signature: a token (401; 403 above viewer), inputs (422),
    path parameters (404), the database (503)."""
    from api.deps import get_db

    codes: set[int] = set()
    calls = _dependency_calls(route.dependant)
    roles = [getattr(c, "required_role", None) for c in calls]
    roles = [r for r in roles if r]
    if roles:
        codes.add(401)
        if any(r != "viewer" for r in roles):
            codes.add(403)
    d = route.dependant
    if d.path_params:
        codes |= {404, 422}
    codes.add(422)                 # inputs, and an unknown query parameter on any route (reject_unknown_query)
    if d.body_params:
        codes.add(400)             # a body that is not JSON at all
    if get_db in calls:
        codes.add(503)
    return codes


def _api_routes(routes):
    """Every APIRoute, also inside included routers (included here without an extra prefix)."""
    from fastapi.routing import APIRoute

    for r in routes:
        if isinstance(r, APIRoute):
            yield r
        elif getattr(r, "original_router", None) is not None:
            yield from _api_routes(r.original_router.routes)


def document_problems(app: FastAPI) -> None:
    """Make the OpenAPI document tell the truth about errors: every problem status a route answers,
    each as ``application/problem+json`` with the Problem schema (FastAPI's default 422 shape is
    replaced: errors here are problem documents)."""
    from fastapi.openapi.utils import get_openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        doc.setdefault("components", {}).setdefault("schemas", {})["Problem"] = PROBLEM_SCHEMA
        for schema_name in ("HTTPValidationError", "ValidationError"):
            doc["components"]["schemas"].pop(schema_name, None)
        for route in _api_routes(app.routes):
            if not route.include_in_schema:
                continue
            for method in route.methods:
                op = doc["paths"].get(route.path_format, {}).get(method.lower())
                if op is None:
                    continue
                codes = _route_codes(route) | set(op.pop("x-problem-codes", []))
                responses = op.setdefault("responses", {})
                for code in sorted(codes):
                    responses[str(code)] = {"description": _DESCRIPTIONS.get(code, "Problem"),
                                            "content": {MEDIA_TYPE: {"schema": PROBLEM_REF}}}
        app.openapi_schema = doc
        return doc

    app.openapi = openapi
