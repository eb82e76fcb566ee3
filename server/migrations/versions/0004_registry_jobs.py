"""policy registry (version per lineage, manifest, calibration, evaluation, command, status reason),
fine-tuning jobs and the job lease

Revision ID: 0004
Revises: 0003
"""

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("version", sa.Integer(), nullable=False, server_default="1"))
        batch_op.add_column(sa.Column("manifest", sa.JSON(), nullable=False, server_default="{}"))
        batch_op.add_column(sa.Column("calibration", sa.JSON(), nullable=False, server_default="{}"))
        batch_op.add_column(sa.Column("evaluation", sa.JSON(), nullable=False, server_default="{}"))
        batch_op.add_column(sa.Column("command", sa.String(length=2048), nullable=True))
        batch_op.add_column(sa.Column("status_reason", sa.String(length=1024), nullable=True))
    # versions already registered: numbered 1, 2, ... per name, in the order they were added
    conn = op.get_bind()
    rows = conn.execute(sa.text("SELECT id, name FROM policy_versions ORDER BY id")).fetchall()
    seen: dict[str, int] = {}
    for row_id, name in rows:
        seen[name] = seen.get(name, 0) + 1
        conn.execute(sa.text("UPDATE policy_versions SET version = :v WHERE id = :i"), {"v": seen[name], "i": row_id})
    # one active version per lineage: older databases may have several (every configured folder was
    # made active); the newest stays active
    for (name,) in conn.execute(
        sa.text("SELECT name FROM policy_versions WHERE status = 'active' GROUP BY name HAVING COUNT(*) > 1")
    ).fetchall():
        keep = conn.execute(
            sa.text("SELECT MAX(id) FROM policy_versions WHERE name = :n AND status = 'active'"), {"n": name}
        ).scalar()
        conn.execute(
            sa.text("UPDATE policy_versions SET status = 'retired' WHERE name = :n AND status = 'active' AND id <> :k"),
            {"n": name, "k": keep},
        )
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.create_unique_constraint("uq_policy_versions_name_version", ["name", "version"])
    op.create_index(
        "uq_policy_versions_one_active",
        "policy_versions",
        ["name"],
        unique=True,
        sqlite_where=sa.text("status = 'active'"),
        postgresql_where=sa.text("status = 'active'"),
    )

    op.create_table(
        "finetune_jobs",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("lineage", sa.String(length=256), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("stage", sa.String(length=32), nullable=True),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("source", sa.String(length=32), nullable=False),
        sa.Column("trigger", sa.String(length=32), nullable=False),
        sa.Column("parent_id", sa.Integer(), sa.ForeignKey("policy_versions.id"), nullable=True),
        sa.Column("version_id", sa.Integer(), sa.ForeignKey("policy_versions.id"), nullable=True),
        sa.Column("since", sa.DateTime(timezone=True), nullable=True),
        sa.Column("data", sa.JSON(), nullable=False),
        sa.Column("evaluation", sa.JSON(), nullable=False),
        sa.Column("gate", sa.JSON(), nullable=False),
        sa.Column("error", sa.String(length=4096), nullable=True),
        sa.Column("command", sa.String(length=2048), nullable=True),
        sa.Column("work_dir", sa.String(length=1024), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("ended_at", sa.DateTime(timezone=True), nullable=True),
    )
    op.create_index("ix_finetune_jobs_lineage", "finetune_jobs", ["lineage"])
    op.create_index("ix_finetune_jobs_status", "finetune_jobs", ["status"])
    op.create_table(
        "job_leases",
        sa.Column("name", sa.String(length=64), primary_key=True),
        sa.Column("owner", sa.String(length=256), nullable=True),
        sa.Column("fence", sa.Integer(), nullable=False),
        sa.Column("expires_at", sa.Float(), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("job_leases")
    op.drop_index("ix_finetune_jobs_status", table_name="finetune_jobs")
    op.drop_index("ix_finetune_jobs_lineage", table_name="finetune_jobs")
    op.drop_table("finetune_jobs")
    op.drop_index("uq_policy_versions_one_active", table_name="policy_versions")
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.drop_constraint("uq_policy_versions_name_version", type_="unique")
        for column in ("status_reason", "command", "evaluation", "calibration", "manifest", "version"):
            batch_op.drop_column(column)
