"""frame_seconds: one row per 16 seconds with packed float64 sums instead of one row per second.

Reading the 1-s means of a 24 h run went from 86 400 rows x 15 columns (0.5-0.9 s, growing with the
run length) to 5 400 rows of one 1.8 kB blob.  Existing per-second rows are converted.
Layout (see ``bench.storage.models.FrameSecond``): little-endian float64 (16, 14), columns
n, n_invalid, sum_dt, sum_gx/gy/gz, sum_ax/ay/az, n_temp, sum_temp, sum_fx/fy/fz.

Revision ID: 0003_frame_second_blocks
Revises: 0002_service
"""
from __future__ import annotations

import numpy as np
import sqlalchemy as sa
from alembic import op

revision = "0003_frame_second_blocks"
down_revision = "0002_service"
branch_labels = None
depends_on = None

BLOCK = 16
FIELDS = ("n", "n_invalid", "sum_dt", "sum_gx", "sum_gy", "sum_gz", "sum_ax", "sum_ay", "sum_az",
          "n_temp", "sum_temp", "sum_fx", "sum_fy", "sum_fz")


def _create_blocks_table() -> None:
    op.create_table(
        "frame_seconds",
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("block", sa.BigInteger(), nullable=False),
        sa.Column("has_freq", sa.Boolean(), nullable=False),
        sa.Column("sums", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_frame_seconds_run_id_runs"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("run_id", "block", name=op.f("pk_frame_seconds")),
    )
    if op.get_bind().dialect.name == "postgresql":
        # room on each page for HOT updates of the block the writer is filling
        op.execute("ALTER TABLE frame_seconds SET (fillfactor = 50)")


def upgrade() -> None:
    conn = op.get_bind()
    old = conn.execute(sa.text(f"SELECT run_id, second, {', '.join(FIELDS)} FROM frame_seconds "
                               "ORDER BY run_id, second")).all()
    op.drop_table("frame_seconds")
    _create_blocks_table()
    blocks: dict[tuple[int, int], tuple[bool, np.ndarray]] = {}
    for row in old:
        run_id, second = row[0], row[1]
        key = (run_id, second - second % BLOCK)
        has_freq, arr = blocks.setdefault(key, (False, np.zeros((BLOCK, len(FIELDS)))))
        values = [0.0 if v is None else float(v) for v in row[2:]]
        arr[second - key[1]] = values
        blocks[key] = (has_freq or row[-1] is not None, arr)
    if blocks:
        table = sa.table("frame_seconds", sa.column("run_id"), sa.column("block"), sa.column("has_freq"),
                         sa.column("sums"))
        op.bulk_insert(table, [{"run_id": r, "block": b, "has_freq": hf, "sums": arr.astype("<f8").tobytes()}
                               for (r, b), (hf, arr) in blocks.items()])


def downgrade() -> None:
    conn = op.get_bind()
    packed = conn.execute(sa.text("SELECT run_id, block, has_freq, sums FROM frame_seconds")).all()
    op.drop_table("frame_seconds")
    cols = [sa.Column("run_id", sa.Integer(), nullable=False), sa.Column("second", sa.BigInteger(), nullable=False)]
    cols += [sa.Column(f, sa.Integer() if f in ("n", "n_invalid", "n_temp") else sa.Float(precision=53),
                       nullable=f.startswith("sum_f")) for f in FIELDS]
    table = op.create_table(
        "frame_seconds", *cols,
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], name=op.f("fk_frame_seconds_run_id_runs"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("run_id", "second", name=op.f("pk_frame_seconds")),
        sqlite_with_rowid=False,
    )
    rows = []
    for run_id, block, has_freq, sums in packed:
        arr = np.frombuffer(sums, dtype="<f8").reshape(BLOCK, len(FIELDS))
        for i in np.nonzero(arr[:, 0] + arr[:, 1] > 0)[0].tolist():
            row = {"run_id": run_id, "second": block + i}
            for j, f in enumerate(FIELDS):
                v = float(arr[i, j])
                row[f] = int(round(v)) if f in ("n", "n_invalid", "n_temp") else (
                    None if f.startswith("sum_f") and not has_freq else v)
            rows.append(row)
    if rows:
        op.bulk_insert(table, rows)
