"""Image frames and pose results; keypoints packed as float32 instead of JSON.

- cameras.keep_images: whether an image frame's picture outlives its pose job (privacy: off by default).
- frames: status 'detecting' (an image frame waiting for its pose job) and pose_model.
- frame_images: the posted picture, the pose job's input.
- observations: the detector's box and score; keypoints move from a JSON column to packed little-endian float32
  (x, y, score) x 17, converted row by row here (and back on downgrade).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np
import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_DTYPE = np.dtype("<f4")
_BATCH = 5000
_OLD_STATUSES = "status IN ('pending', 'done', 'failed')"
_NEW_STATUSES = "status IN ('detecting', 'pending', 'done', 'failed')"


def _convert_keypoints(source: str, target: str, convert: object) -> None:
    """Copy observations.<source> into observations.<target> through `convert`, a batch of rows at a time."""
    connection = op.get_bind()
    table = sa.table("observations", sa.column("id"), sa.column(source), sa.column(target))
    last_id = -1
    while True:
        rows = connection.execute(
            sa.select(table.c.id, table.c[source])
            .where(table.c.id > last_id, table.c[source].is_not(None))
            .order_by(table.c.id)
            .limit(_BATCH)
        ).all()
        if not rows:
            return
        connection.execute(
            table.update().where(table.c.id == sa.bindparam("row_id")).values({target: sa.bindparam("value")}),
            [{"row_id": row_id, "value": convert(value)} for row_id, value in rows],  # type: ignore[operator]
        )
        last_id = rows[-1][0]


def _pack(value: object) -> bytes:
    data = json.loads(value) if isinstance(value, str | bytes) else value
    return np.asarray(data, dtype=_DTYPE).reshape(17, 3).tobytes()


def _unpack(value: bytes) -> str:
    values = [float(str(v)) for v in np.frombuffer(value, dtype=_DTYPE)]
    return json.dumps([values[k : k + 3] for k in range(0, 51, 3)])


def upgrade() -> None:
    with op.batch_alter_table("cameras") as batch:
        batch.add_column(sa.Column("keep_images", sa.Boolean(), server_default=sa.text("false"), nullable=False))
    with op.batch_alter_table("frames") as batch:
        batch.add_column(sa.Column("pose_model", sa.String(length=64), nullable=True))
        batch.drop_constraint(op.f("ck_frames_status"), type_="check")
        batch.create_check_constraint(op.f("ck_frames_status"), _NEW_STATUSES)
    with op.batch_alter_table("observations") as batch:
        batch.add_column(sa.Column("keypoints_f32", sa.LargeBinary(), nullable=True))
        for name in ("box_left_px", "box_top_px", "box_right_px", "box_bottom_px", "detection_score"):
            batch.add_column(sa.Column(name, sa.Double(), nullable=True))
    _convert_keypoints("keypoints", "keypoints_f32", _pack)
    with op.batch_alter_table("observations") as batch:
        batch.drop_column("keypoints")
    op.create_table(
        "frame_images",
        sa.Column("frame_id", sa.Uuid(), nullable=False),
        sa.Column("content_type", sa.String(length=32), nullable=False),
        sa.Column("width_px", sa.Integer(), nullable=False),
        sa.Column("height_px", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("content_type IN ('image/jpeg', 'image/png')", name=op.f("ck_frame_images_content_type")),
        sa.ForeignKeyConstraint(
            ["frame_id"], ["frames.id"], name=op.f("fk_frame_images_frame_id_frames"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("frame_id", name=op.f("pk_frame_images")),
    )


def downgrade() -> None:
    op.drop_table("frame_images")
    with op.batch_alter_table("observations") as batch:
        batch.add_column(sa.Column("keypoints", sa.JSON(), nullable=True))
    _convert_keypoints("keypoints_f32", "keypoints", _unpack)
    with op.batch_alter_table("observations") as batch:
        for name in ("keypoints_f32", "box_left_px", "box_top_px", "box_right_px", "box_bottom_px", "detection_score"):
            batch.drop_column(name)
    # Image frames cannot exist without the 'detecting'/'image' machinery: drop those still waiting for pose.
    op.execute("DELETE FROM frames WHERE status = 'detecting'")
    with op.batch_alter_table("frames") as batch:
        batch.drop_constraint(op.f("ck_frames_status"), type_="check")
        batch.create_check_constraint(op.f("ck_frames_status"), _OLD_STATUSES)
        batch.drop_column("pose_model")
    with op.batch_alter_table("cameras") as batch:
        batch.drop_column("keep_images")
