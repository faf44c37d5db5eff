"""group_barriers: the completion barriers of Dramatiq groups (a station scan's heads)

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-07
"""

from alembic import op
import sqlalchemy as sa


revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'group_barriers',
        sa.Column('key', sa.String(length=100), nullable=False),
        sa.Column('value', sa.Integer(), nullable=False),
        sa.Column('expires_at', sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint('key'),
    )
    with op.batch_alter_table('group_barriers', schema=None) as batch_op:
        batch_op.create_index('ix_group_barriers_expires_at', ['expires_at'])


def downgrade() -> None:
    with op.batch_alter_table('group_barriers', schema=None) as batch_op:
        batch_op.drop_index('ix_group_barriers_expires_at')
    op.drop_table('group_barriers')
