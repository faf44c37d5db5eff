"""jobs.dispatched_at: the transactional outbox (a job whose message is not yet sent has none);
jobs.heartbeat_at: the running worker's lease

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-02
"""

from alembic import op
import sqlalchemy as sa


revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('dispatched_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.create_index('ix_jobs_dispatched_at', ['dispatched_at'])
    # Jobs created before the outbox were sent when they were created.
    op.execute("UPDATE jobs SET dispatched_at = created_at")


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_index('ix_jobs_dispatched_at')
        batch_op.drop_column('heartbeat_at')
        batch_op.drop_column('dispatched_at')
