"""part types (recipes) and the scans' inspection: part_type_id, verdict, features

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-02
"""

from alembic import op
import sqlalchemy as sa


revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('part_types',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('name', sa.String(length=200), nullable=False),
    sa.Column('station', sa.String(length=100), nullable=False),
    sa.Column('material', sa.String(length=200), nullable=False),
    sa.Column('part_sha256', sa.String(length=64), nullable=False),
    sa.Column('mesh_sha256', sa.String(length=64), nullable=False),
    sa.Column('selected', sa.Boolean(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('part_types', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_part_types_station'), ['station'], unique=False)
    with op.batch_alter_table('scans', schema=None) as batch_op:
        batch_op.add_column(sa.Column('part_type_id', sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column('verdict', sa.String(length=20), nullable=True))
        batch_op.add_column(sa.Column('features', sa.JSON(), nullable=True))
        batch_op.create_foreign_key('scans_part_type_id_fkey', 'part_types', ['part_type_id'], ['id'])


def downgrade() -> None:
    with op.batch_alter_table('scans', schema=None) as batch_op:
        batch_op.drop_constraint('scans_part_type_id_fkey', type_='foreignkey')
        batch_op.drop_column('features')
        batch_op.drop_column('verdict')
        batch_op.drop_column('part_type_id')
    with op.batch_alter_table('part_types', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_part_types_station'))
    op.drop_table('part_types')
