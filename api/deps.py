"""Shared endpoint plumbing: the database handle and lookups that answer 404 with a clear message."""
from __future__ import annotations

from fastapi import Request
from sqlalchemy.orm import Session

from api.problems import Problem
from bench.storage.db import Database
from bench.storage.models import Run


async def get_db(request: Request) -> Database:
    return request.app.state.db


def run_or_404(session: Session, run_id: int) -> Run:
    run = session.get(Run, run_id)
    if run is None:
        raise Problem(404, "Run not found", f"run {run_id} does not exist")
    return run


def stale_after_s(request: Request) -> float:
    return float(request.app.state.stale_after_s)
