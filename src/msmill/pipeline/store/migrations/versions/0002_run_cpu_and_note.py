"""runs: CPU time and a note (checkpoint resume, issue 35)

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-04

"""
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = '0002'
down_revision: str | Sequence[str] | None = '0001'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Upgrade schema."""
    with op.batch_alter_table('runs') as batch:
        batch.add_column(sa.Column('cpu_s', sa.Float(), nullable=True))
        batch.add_column(sa.Column('note', sa.Text(), nullable=True))


def downgrade() -> None:
    """Downgrade schema."""
    with op.batch_alter_table('runs') as batch:
        batch.drop_column('note')
        batch.drop_column('cpu_s')
