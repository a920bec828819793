"""several gyros in one chamber: a multi-gyro run is a parent run (plan, steps, status, chamber and
table telemetry) with one child run per gyro (its frames, probes, supply, segments, gaps and fits),
``runs.parent_id`` naming the parent and ``runs.slot`` the fixture slot.

Revision ID: 0005_gyro_units
Revises: 0004_analysis_jobs
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005_gyro_units"
down_revision = "0004_analysis_jobs"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # plain ADD / DROP COLUMN, never a batch rebuild of ``runs``: on SQLite a rebuild drops the old table,
    # and with foreign keys enforced that cascade-deletes every run's data.  For the same reason
    # ``parent_id`` carries no database foreign key (SQLite cannot drop a column named in one without a
    # rebuild); ``bench.storage.queries.create_run`` is the one writer of it.
    op.add_column("runs", sa.Column("parent_id", sa.Integer(), nullable=True))
    op.add_column("runs", sa.Column("slot", sa.String(length=32), nullable=True))
    op.create_index("ix_runs_parent_id", "runs", ["parent_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_runs_parent_id", table_name="runs")
    op.drop_column("runs", "slot")          # SQLite >= 3.35
    op.drop_column("runs", "parent_id")
