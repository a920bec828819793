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
