"""An arm's cell edited in the pendant: its keep-out boxes and planes, stored under its name.

- ``cells``: one row per arm whose cell was edited (``PUT /cell``); its boxes and planes (None:
  the start-up settings apply again) and a revision that refuses edits made from an older view.

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "cells",
        sa.Column("name", sa.String(200), primary_key=True),
        sa.Column("keep_out_boxes", sa.JSON, nullable=True),
        sa.Column("cell_planes", sa.JSON, nullable=True),
        sa.Column("revision", sa.Integer, nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("cells")
