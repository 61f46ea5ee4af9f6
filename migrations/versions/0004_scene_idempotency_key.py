"""Scene uploads take an Idempotency-Key: a retried upload returns the scene the first one made.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('idempotency_key', sa.String(length=256), nullable=True))
        batch_op.add_column(sa.Column('request_hash', sa.String(length=64), nullable=True))
        batch_op.create_unique_constraint('uq_scenes_owner_idempotency_key', ['owner', 'idempotency_key'])


def downgrade() -> None:
    with op.batch_alter_table('scenes', schema=None) as batch_op:
        batch_op.drop_constraint('uq_scenes_owner_idempotency_key', type_='unique')
        batch_op.drop_column('request_hash')
        batch_op.drop_column('idempotency_key')
