"""Operator service: control requests, live run progress, worker presence per bench, analyses.

* ``run_requests``: operator requests (stop / abort / pause / resume) written by the API and consumed,
  in order, by the worker executing the run (``consumed_at`` set when the engine got it).
* ``runs.live``: progress document the worker refreshes with each heartbeat (percent, step, ETA).
* ``benches.worker`` / ``heartbeat_at`` / ``state``: which worker serves the bench, when it was last
  alive and what it reports (idle / busy, current run, devices).
* ``analyses``: long computations started through the API (close-the-loop), with status and result.

Revision ID: 0002_service
Revises: 0001
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

JSON_T = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")

revision = "0002_service"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("runs", sa.Column("live", JSON_T, nullable=True))
    op.add_column("benches", sa.Column("worker", sa.String(length=128), nullable=True))
    op.add_column("benches", sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True))
    op.add_column("benches", sa.Column("state", JSON_T, nullable=True))
    op.create_table(
        "run_requests",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("command", sa.String(length=16), nullable=False),
        sa.Column("requested_by", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("consumed_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint("command IN ('stop', 'abort', 'pause', 'resume')", name=op.f("ck_run_requests_command")),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_run_requests_run_id_runs"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_run_requests")),
    )
    op.create_index(op.f("ix_run_requests_run_id_consumed_at"), "run_requests", ["run_id", "consumed_at"])
    op.create_table(
        "analyses",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=32), nullable=False),
        sa.Column("gyro_id", sa.String(length=64), nullable=True),
        sa.Column("request", JSON_T, nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("result", JSON_T, nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("requested_by", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint("status IN ('queued', 'running', 'done', 'failed')", name=op.f("ck_analyses_status")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_analyses")),
    )


def downgrade() -> None:
    op.drop_table("analyses")
    op.drop_index(op.f("ix_run_requests_run_id_consumed_at"), table_name="run_requests")
    op.drop_table("run_requests")
    with op.batch_alter_table("benches") as batch:
        batch.drop_column("state")
        batch.drop_column("heartbeat_at")
        batch.drop_column("worker")
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("live")
