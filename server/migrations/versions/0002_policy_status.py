"""policy versions: status (candidate, active, retired) and parent

Revision ID: 0002
Revises: 0001
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("status", sa.String(length=16), nullable=False, server_default="active"))
        batch_op.add_column(sa.Column("parent_id", sa.Integer(), nullable=True))
        batch_op.create_index(batch_op.f("ix_policy_versions_status"), ["status"], unique=False)
        batch_op.create_foreign_key("fk_policy_versions_parent", "policy_versions", ["parent_id"], ["id"])


def downgrade() -> None:
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.drop_constraint("fk_policy_versions_parent", type_="foreignkey")
        batch_op.drop_index(batch_op.f("ix_policy_versions_status"))
        batch_op.drop_column("parent_id")
        batch_op.drop_column("status")
