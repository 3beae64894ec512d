"""observations.appearance: what a person found in an image looks like (issue 16), so that a camera posting one
image every few seconds gets one person's observations linked into one individual (service.geometry.tracks).

Nullable: people posted as keypoints, and everyone stored before this revision, have none and are linked by
times and positions only, as before. No data changes on upgrade or downgrade.

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-28
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.add_column(sa.Column("appearance", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.drop_column("appearance")
