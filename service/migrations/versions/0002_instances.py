"""Several service instances on one database: who runs each job and capture, and who is alive.

- ``instances``: one row per running ``teachpath serve`` process, its heartbeat refreshed every
  few seconds; an instance whose heartbeat is stale has stopped.
- ``jobs.owner`` and ``captures.owner``: the instance that runs them. Start-up recovery fails only
  the jobs (and ends only the captures) of instances that stopped, never a live one's.
- ``artifacts.size`` becomes a 64-bit integer (a 1M-point scan's arrays are tens of MB; a
  session's recordings can pass 2 GB, which PostgreSQL's INTEGER cannot hold).

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    when = sa.DateTime(timezone=True)
    op.create_table(
        "instances",
        sa.Column("id", sa.String(64), primary_key=True),
        sa.Column("host", sa.String(200), nullable=False),
        sa.Column("pid", sa.Integer, nullable=False),
        sa.Column("started_at", when, nullable=False),
        sa.Column("heartbeat_at", when, nullable=False),
    )
    with op.batch_alter_table("jobs") as jobs:
        jobs.add_column(sa.Column("owner", sa.String(64), nullable=True))
        jobs.create_index("ix_jobs_owner", ["owner"])
    with op.batch_alter_table("captures") as captures:
        captures.add_column(sa.Column("owner", sa.String(64), nullable=True))
    with op.batch_alter_table("artifacts") as artifacts:
        artifacts.alter_column(
            "size", existing_type=sa.Integer, type_=sa.BigInteger, existing_nullable=False
        )


def downgrade() -> None:
    with op.batch_alter_table("artifacts") as artifacts:
        artifacts.alter_column(
            "size", existing_type=sa.BigInteger, type_=sa.Integer, existing_nullable=False
        )
    with op.batch_alter_table("captures") as captures:
        captures.drop_column("owner")
    with op.batch_alter_table("jobs") as jobs:
        jobs.drop_index("ix_jobs_owner")
        jobs.drop_column("owner")
    op.drop_table("instances")
