"""calibration_sets.job_id dropped: calibration sets come from uploads

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""

from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('calibration_sets', schema=None) as batch_op:
        batch_op.drop_column('job_id')  # its foreign key goes with it


def downgrade() -> None:
    with op.batch_alter_table('calibration_sets', schema=None) as batch_op:
        batch_op.add_column(sa.Column('job_id', sa.VARCHAR(length=32), nullable=True))
        batch_op.create_foreign_key('calibration_sets_job_id_fkey', 'jobs', ['job_id'], ['id'])
