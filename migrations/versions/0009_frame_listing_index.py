"""An index for listing a camera's frames by capture time (GET /v1/cameras/{camera_id}/frames).

The list pages newest first by (timestamp, id) with a keyset cursor; this index makes each page a range scan of one
camera's frames however many it has. Frames arrive roughly in capture order, so the index grows at its right end
per camera on the ingest path. No data changes.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

INDEX = "ix_frames_camera_id_timestamp_id"


def upgrade() -> None:
    op.create_index(INDEX, "frames", ["camera_id", "timestamp", "id"])


def downgrade() -> None:
    op.drop_index(INDEX, table_name="frames")
