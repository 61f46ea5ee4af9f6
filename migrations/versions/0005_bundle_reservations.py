"""Bundles: the bytes a job may write are reserved against its owner's quota, and one render or
bundle job at a time makes a given file of a job (issue 49).

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None

FILE_IN_THE_MAKING = "type IN ('render', 'bundle') AND state IN ('queued', 'running')"  # as service.models


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('reserved_bytes', sa.BigInteger(), server_default='0', nullable=False))
    op.create_index('uq_jobs_file_in_the_making', 'jobs', ['parent_job_id', 'request_hash'], unique=True,
                    sqlite_where=sa.text(FILE_IN_THE_MAKING), postgresql_where=sa.text(FILE_IN_THE_MAKING))


def downgrade() -> None:
    op.drop_index('uq_jobs_file_in_the_making', table_name='jobs')
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('reserved_bytes')
