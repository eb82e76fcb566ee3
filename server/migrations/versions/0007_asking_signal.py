"""the request a takeover answers: the asking signal's name, its score and threshold, the paper's U

Revision ID: 0007
Revises: 0006
"""

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # nullable: a takeover recorded before reads None in each (not recorded then)
    with op.batch_alter_table("segments") as batch:
        batch.add_column(sa.Column("signal", sa.String(length=64), nullable=True))
        batch.add_column(sa.Column("score", sa.Float(), nullable=True))
        batch.add_column(sa.Column("threshold", sa.Float(), nullable=True))
        batch.add_column(sa.Column("paper_u", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("segments") as batch:
        for column in ("paper_u", "threshold", "score", "signal"):
            batch.drop_column(column)
