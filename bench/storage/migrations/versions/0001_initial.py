"""Initial schema of the runs database (see bench/storage/models.py for the meaning of each table).

Revision ID: 0001
Revises: 
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

JSON_T = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")

revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('benches',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=64), nullable=False),
    sa.Column('config', JSON_T, nullable=False),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_benches')),
    sa.UniqueConstraint('name', name=op.f('uq_benches_name'))
    )
    op.create_table('gyros',
    sa.Column('gyro_id', sa.String(length=64), nullable=False),
    sa.Column('type', sa.String(length=64), nullable=False),
    sa.Column('notes', sa.Text(), nullable=False),
    sa.PrimaryKeyConstraint('gyro_id', name=op.f('pk_gyros'))
    )
    op.create_table('fits',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('gyro_id', sa.String(length=64), nullable=False),
    sa.Column('run_ids', JSON_T, nullable=False),
    sa.Column('model', sa.String(length=32), nullable=False),
    sa.Column('channel', sa.String(length=16), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('coefficients', JSON_T, nullable=False),
    sa.Column('result', JSON_T, nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('accepted', sa.Boolean(), nullable=False),
    sa.ForeignKeyConstraint(['gyro_id'], ['gyros.gyro_id'], name=op.f('fk_fits_gyro_id_gyros')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_fits')),
    sa.UniqueConstraint('gyro_id', 'model', 'channel', 'version', name=op.f('uq_fits_gyro_id_model_channel_version'))
    )
    op.create_table('runs',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('procedure', sa.String(length=128), nullable=False),
    sa.Column('parameters', JSON_T, nullable=False),
    sa.Column('config_snapshot', JSON_T, nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('operator', sa.String(length=64), nullable=False),
    sa.Column('gyro_id', sa.String(length=64), nullable=True),
    sa.Column('bench_id', sa.Integer(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('start_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('current_step', sa.Integer(), nullable=True),
    sa.Column('progress', sa.Float(precision=53), nullable=False),
    sa.Column('checkpoint', JSON_T, nullable=True),
    sa.Column('worker', sa.String(length=128), nullable=True),
    sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('error', sa.Text(), nullable=True),
    sa.CheckConstraint("status IN ('queued', 'running', 'paused', 'stopping', 'completed', 'aborted', 'failed', 'suspended')", name=op.f('ck_runs_status')),
    sa.CheckConstraint('progress >= 0 AND progress <= 1', name=op.f('ck_runs_progress')),
    sa.ForeignKeyConstraint(['bench_id'], ['benches.id'], name=op.f('fk_runs_bench_id_benches')),
    sa.ForeignKeyConstraint(['gyro_id'], ['gyros.gyro_id'], name=op.f('fk_runs_gyro_id_gyros')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_runs'))
    )
    op.create_index(op.f('ix_runs_gyro_id'), 'runs', ['gyro_id'], unique=False)
    op.create_index(op.f('ix_runs_status_start_at'), 'runs', ['status', 'start_at'], unique=False)
    op.create_table('events',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('t_bench', sa.Float(precision=53), nullable=True),
    sa.Column('wall_time', sa.DateTime(timezone=True), nullable=False),
    sa.Column('kind', sa.String(length=32), nullable=False),
    sa.Column('message', sa.Text(), nullable=False),
    sa.Column('data', JSON_T, nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_events_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_events'))
    )
    op.create_index(op.f('ix_events_run_id_t_bench'), 'events', ['run_id', 't_bench'], unique=False)
    op.create_table('frame_chunks',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('first_index', sa.BigInteger(), nullable=False),
    sa.Column('count', sa.Integer(), nullable=False),
    sa.Column('t_first', sa.Float(precision=53), nullable=False),
    sa.Column('t_last', sa.Float(precision=53), nullable=False),
    sa.Column('frame_kind', sa.String(length=16), nullable=False),
    sa.Column('frame_size', sa.Integer(), nullable=False),
    sa.Column('raw', sa.LargeBinary(), nullable=False),
    sa.Column('dt_us', sa.LargeBinary(), nullable=False),
    sa.Column('temp_centi', sa.LargeBinary(), nullable=False),
    sa.CheckConstraint('count > 0', name=op.f('ck_frame_chunks_count')),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_frame_chunks_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_frame_chunks')),
    sa.UniqueConstraint('run_id', 'first_index', name=op.f('uq_frame_chunks_run_id_first_index'))
    )
    op.create_table('frame_cursors',
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('next_index', sa.BigInteger(), nullable=False),
    sa.Column('batch_seq', sa.BigInteger(), nullable=False),
    sa.Column('writer_token', sa.String(length=64), nullable=False),
    sa.Column('t_last', sa.Float(precision=53), nullable=True),
    sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_frame_cursors_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('run_id', name=op.f('pk_frame_cursors'))
    )
    op.create_table('frame_seconds',
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('second', sa.BigInteger(), nullable=False),
    sa.Column('n', sa.Integer(), nullable=False),
    sa.Column('n_invalid', sa.Integer(), nullable=False),
    sa.Column('sum_dt', sa.Float(precision=53), nullable=False),
    sa.Column('sum_gx', sa.Float(precision=53), nullable=False),
    sa.Column('sum_gy', sa.Float(precision=53), nullable=False),
    sa.Column('sum_gz', sa.Float(precision=53), nullable=False),
    sa.Column('sum_ax', sa.Float(precision=53), nullable=False),
    sa.Column('sum_ay', sa.Float(precision=53), nullable=False),
    sa.Column('sum_az', sa.Float(precision=53), nullable=False),
    sa.Column('n_temp', sa.Integer(), nullable=False),
    sa.Column('sum_temp', sa.Float(precision=53), nullable=False),
    sa.Column('sum_fx', sa.Float(precision=53), nullable=True),
    sa.Column('sum_fy', sa.Float(precision=53), nullable=True),
    sa.Column('sum_fz', sa.Float(precision=53), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_frame_seconds_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('run_id', 'second', name=op.f('pk_frame_seconds')),
    sqlite_with_rowid=False
    )
    op.create_table('gaps',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('t_from', sa.Float(precision=53), nullable=False),
    sa.Column('t_to', sa.Float(precision=53), nullable=False),
    sa.Column('reason', sa.String(length=64), nullable=False),
    sa.Column('frames_missing', sa.BigInteger(), nullable=True),
    sa.Column('after_index', sa.BigInteger(), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_gaps_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_gaps'))
    )
    op.create_index(op.f('ix_gaps_run_id_t_from'), 'gaps', ['run_id', 't_from'], unique=False)
    op.create_table('probe_readings',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('t', sa.Float(precision=53), nullable=False),
    sa.Column('name', sa.String(length=32), nullable=False),
    sa.Column('serial', sa.String(length=16), nullable=False),
    sa.Column('celsius', sa.Float(precision=53), nullable=True),
    sa.Column('fault', sa.String(length=128), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_probe_readings_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_probe_readings'))
    )
    op.create_index(op.f('ix_probe_readings_run_id_name_t'), 'probe_readings', ['run_id', 'name', 't'], unique=False)
    op.create_table('segments',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('step_index', sa.Integer(), nullable=True),
    sa.Column('kind', sa.String(length=16), nullable=False),
    sa.Column('temperature_c', sa.Float(precision=53), nullable=True),
    sa.Column('orientation', sa.String(length=32), nullable=True),
    sa.Column('outer_deg', sa.Float(precision=53), nullable=True),
    sa.Column('inner_deg', sa.Float(precision=53), nullable=True),
    sa.Column('repetition', sa.Integer(), nullable=False),
    sa.Column('t_start', sa.Float(precision=53), nullable=False),
    sa.Column('t_end', sa.Float(precision=53), nullable=True),
    sa.Column('labels', JSON_T, nullable=True),
    sa.CheckConstraint("kind IN ('soak', 'record', 'ramp', 'settle', 'move')", name=op.f('ck_segments_kind')),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_segments_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_segments'))
    )
    op.create_index(op.f('ix_segments_run_id_t_start'), 'segments', ['run_id', 't_start'], unique=False)
    op.create_table('steps',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('index', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=128), nullable=False),
    sa.Column('kind', sa.String(length=32), nullable=False),
    sa.Column('params', JSON_T, nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('started_t', sa.Float(precision=53), nullable=True),
    sa.Column('finished_t', sa.Float(precision=53), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_steps_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_steps')),
    sa.UniqueConstraint('run_id', 'index', name=op.f('uq_steps_run_id_index'))
    )
    op.create_table('suspensions',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('t_from', sa.Float(precision=53), nullable=False),
    sa.Column('t_to', sa.Float(precision=53), nullable=True),
    sa.Column('reason', sa.Text(), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_suspensions_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_suspensions'))
    )
    op.create_index(op.f('ix_suspensions_run_id'), 'suspensions', ['run_id'], unique=False)
    op.create_table('telemetry',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('t', sa.Float(precision=53), nullable=False),
    sa.Column('device', sa.String(length=16), nullable=False),
    sa.Column('chamber_pv', sa.Float(precision=53), nullable=True),
    sa.Column('chamber_sp', sa.Float(precision=53), nullable=True),
    sa.Column('chamber_ramp_sp', sa.Float(precision=53), nullable=True),
    sa.Column('chamber_mode', sa.Integer(), nullable=True),
    sa.Column('chamber_alarm', sa.Integer(), nullable=True),
    sa.Column('axis1_pos', sa.Float(precision=53), nullable=True),
    sa.Column('axis1_rate', sa.Float(precision=53), nullable=True),
    sa.Column('axis2_pos', sa.Float(precision=53), nullable=True),
    sa.Column('axis2_rate', sa.Float(precision=53), nullable=True),
    sa.Column('psu_volts', sa.Float(precision=53), nullable=True),
    sa.Column('psu_amps', sa.Float(precision=53), nullable=True),
    sa.Column('psu_on', sa.Boolean(), nullable=True),
    sa.CheckConstraint("device IN ('chamber', 'turntable', 'psu')", name=op.f('ck_telemetry_device')),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_telemetry_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_telemetry'))
    )
    op.create_index(op.f('ix_telemetry_run_id_device_t'), 'telemetry', ['run_id', 'device', 't'], unique=False)
    if op.get_bind().dialect.name == "postgresql":
        # raw float frames do not compress: store them out of line without trying pglz each time
        op.execute("ALTER TABLE frame_chunks ALTER COLUMN raw SET STORAGE EXTERNAL")


def downgrade() -> None:
    op.drop_table('telemetry')
    op.drop_table('suspensions')
    op.drop_table('steps')
    op.drop_table('segments')
    op.drop_table('probe_readings')
    op.drop_table('gaps')
    op.drop_table('frame_seconds')
    op.drop_table('frame_cursors')
    op.drop_table('frame_chunks')
    op.drop_table('events')
    op.drop_table('runs')
    op.drop_table('fits')
    op.drop_table('gyros')
    op.drop_table('benches')
