"""The schema of the releases before Alembic: sessions, artifacts, jobs, captures.

A database made by one of them has these tables already, with or without the nullable columns
added over time (they were added on start by ALTER TABLE). So this first migration creates what
is missing and adds what a table lacks, and brings any earlier teachpath database, or an empty
one, to the same schema.

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def _tables() -> list[sa.Table]:
    meta = sa.MetaData()
    when = sa.DateTime(timezone=True)
    return [
        sa.Table(
            "sessions",
            meta,
            sa.Column("id", sa.String(32), primary_key=True),
            sa.Column("name", sa.String(200), nullable=False),
            sa.Column("created_at", when, nullable=False),
            sa.Column("deleted_at", when, nullable=True),
            sa.Column("recording_id", sa.String(32), nullable=True),
            sa.Column("scan_id", sa.String(32), nullable=True),
            sa.Column("T_base_tracker", sa.JSON, nullable=True),
            sa.Column("T_scan_tracker", sa.JSON, nullable=True),
            sa.Column("tip_offset_m", sa.JSON, nullable=True),
            sa.Column("calibration_report", sa.JSON, nullable=True),
        ),
        sa.Table(
            "artifacts",
            meta,
            sa.Column("id", sa.String(32), primary_key=True),
            sa.Column("session_id", sa.String(32), sa.ForeignKey("sessions.id"), nullable=False),
            sa.Column("kind", sa.String(20), nullable=False),
            sa.Column("created_at", when, nullable=False),
            sa.Column("inputs", sa.JSON, nullable=False),
            sa.Column("params", sa.JSON, nullable=False),
            sa.Column("summary", sa.JSON, nullable=False),
            sa.Column("path", sa.String(300), nullable=False),
            sa.Column("sha256", sa.String(64), nullable=False),
            sa.Column("size", sa.Integer, nullable=False),
            sa.Column("source_name", sa.String(300), nullable=True),
            sa.Index("ix_artifacts_session_id", "session_id"),
            sa.Index("ix_artifacts_kind", "kind"),
        ),
        sa.Table(
            "jobs",
            meta,
            sa.Column("id", sa.String(32), primary_key=True),
            sa.Column("session_id", sa.String(32), sa.ForeignKey("sessions.id"), nullable=False),
            sa.Column("kind", sa.String(20), nullable=False),
            sa.Column("state", sa.String(12), nullable=False),
            sa.Column("progress", sa.Float, nullable=False),
            sa.Column("created_at", when, nullable=False),
            sa.Column("started_at", when, nullable=True),
            sa.Column("finished_at", when, nullable=True),
            sa.Column("params", sa.JSON, nullable=False),
            sa.Column("result", sa.JSON, nullable=True),
            sa.Column("error", sa.JSON, nullable=True),
            sa.Index("ix_jobs_session_id", "session_id"),
            sa.Index("ix_jobs_state", "state"),
        ),
        sa.Table(
            "captures",
            meta,
            sa.Column("id", sa.String(32), primary_key=True),
            sa.Column("session_id", sa.String(32), sa.ForeignKey("sessions.id"), nullable=False),
            sa.Column("source", sa.JSON, nullable=False),
            sa.Column("state", sa.String(12), nullable=False),
            sa.Column("created_at", when, nullable=False),
            sa.Column("n_samples", sa.Integer, nullable=False),
            sa.Column("path", sa.String(300), nullable=False),
            sa.Column("recording_id", sa.String(32), nullable=True),
            sa.Column("error", sa.String(500), nullable=True),
            sa.Index("ix_captures_session_id", "session_id"),
        ),
    ]


def upgrade() -> None:
    bind = op.get_bind()
    inspector = sa.inspect(bind)
    present = set(inspector.get_table_names())
    for table in _tables():
        if table.name not in present:
            table.create(bind)
            continue
        have = {column["name"] for column in inspector.get_columns(table.name)}
        for column in table.columns:
            if column.name in have:
                continue
            if not column.nullable:
                raise RuntimeError(
                    f"the database lacks the non-nullable column {table.name}.{column.name}: it "
                    "was not made by teachpath, or by an incompatible version"
                )
            op.add_column(table.name, sa.Column(column.name, column.type, nullable=True))


def downgrade() -> None:
    for name in ("captures", "jobs", "artifacts", "sessions"):
        op.drop_table(name)
