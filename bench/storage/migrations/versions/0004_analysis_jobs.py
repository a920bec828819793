"""analyses become durable jobs: a worker lease (worker, heartbeat_at), started_at, attempts, the fit a
job produced or rendered (fit_id) and the report page rendered once by the job (report_html).

Fits, close-the-loop analyses and report rendering run in workers (``bench.jobs``), never in the API
process.  An analysis left ``running`` by the old in-process thread has no heartbeat and is claimed
again by the first worker that looks.

Revision ID: 0004_analysis_jobs
Revises: 0003_frame_second_blocks
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004_analysis_jobs"
down_revision = "0003_frame_second_blocks"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("analyses") as batch:
        batch.add_column(sa.Column("worker", sa.String(length=128), nullable=True))
        batch.add_column(sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("started_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("attempts", sa.Integer(), server_default="0", nullable=False))
        batch.add_column(sa.Column("fit_id", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("report_html", sa.Text(), nullable=True))
    op.create_index("ix_analyses_status_id", "analyses", ["status", "id"], unique=False)
    op.create_index("ix_analyses_fit_id", "analyses", ["fit_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_analyses_fit_id", table_name="analyses")
    op.drop_index("ix_analyses_status_id", table_name="analyses")
    with op.batch_alter_table("analyses") as batch:
        for col in ("report_html", "fit_id", "attempts", "started_at", "heartbeat_at", "worker"):
            batch.drop_column(col)
