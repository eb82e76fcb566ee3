"""operator labels on takeover segments: good/bad, discarded, a note, who set them and when

Revision ID: 0006
Revises: 0005
"""

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("segments") as batch:
        batch.add_column(sa.Column("label", sa.String(length=8), nullable=True))
        batch.add_column(sa.Column("discarded", sa.Boolean(), nullable=False, server_default=sa.false()))
        batch.add_column(sa.Column("note", sa.String(length=500), nullable=True))
        batch.add_column(sa.Column("labelled_by", sa.String(length=128), nullable=True))
        batch.add_column(sa.Column("labelled_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("segments") as batch:
        for column in ("labelled_at", "labelled_by", "note", "discarded", "label"):
            batch.drop_column(column)
