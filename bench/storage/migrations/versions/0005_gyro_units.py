"""several gyros in one chamber: a multi-gyro run is a parent run (plan, steps, status, chamber and
table telemetry) with one child run per gyro (its frames, probes, supply, segments, gaps and fits),
``runs.parent_id`` pointing to the parent and ``runs.slot`` naming the fixture slot.

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
    with op.batch_alter_table("runs") as batch:
        batch.add_column(sa.Column("parent_id", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("slot", sa.String(length=32), nullable=True))
        batch.create_foreign_key("fk_runs_parent_id_runs", "runs", ["parent_id"], ["id"], ondelete="CASCADE")
        batch.create_index("ix_runs_parent_id", ["parent_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.drop_index("ix_runs_parent_id")
        batch.drop_constraint("fk_runs_parent_id_runs", type_="foreignkey")
        batch.drop_column("slot")
        batch.drop_column("parent_id")
