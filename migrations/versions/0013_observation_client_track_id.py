"""observations.client_track_id: the id a keypoint client's tracker gave a posted person, so that a camera posting
keypoints every few seconds gets one person's sightings linked into one individual (service.geometry.tracks).

Nullable and unindexed: people posted without one, people found in images and everyone stored before this revision
have none and are linked by times, positions and appearance, as before; the id is read only by primary key with a
calibration's sample. No data changes on upgrade or downgrade.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-28
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.add_column(sa.Column("client_track_id", sa.String(64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.drop_column("client_track_id")
