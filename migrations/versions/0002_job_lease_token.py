"""Jobs get a lease (fencing) token, so one runner at a time writes to a job, and an optional
completion webhook URL.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('lease_token', sa.Integer(), server_default='0', nullable=False))
        batch_op.add_column(sa.Column('webhook_url', sa.String(length=2048), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('webhook_url')
        batch_op.drop_column('lease_token')
