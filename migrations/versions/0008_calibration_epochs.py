"""Calibration epochs: a camera that moved (or was reset) starts its calibration again.

Cameras get their epoch (1 for every camera stored so far), why it was opened, when the camera moved and how
many moves were detected; people and
calibration versions get the epoch they belong to (1); the sampling index starts with (camera_id, epoch); the
movement test keeps its state per camera in `movement_monitors`. No data changes on upgrade beyond the defaults.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-25
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD_SAMPLING_INDEX = "ix_observations_camera_id_usable_cell_sample_key"
OLD_SAMPLING_COLUMNS = ["camera_id", "usable", "cell", "sample_key"]
SAMPLING_INDEX = "ix_observations_camera_id_epoch_usable_cell_sample_key"
SAMPLING_COLUMNS = ["camera_id", "epoch", "usable", "cell", "sample_key"]
EPOCH_REASONS = "('camera_moved', 'reset', 'image_size_changed')"


def _epoch_column() -> sa.Column:
    return sa.Column("epoch", sa.Integer(), nullable=False, server_default=sa.text("1"))


def _sampling_index(name: str, columns: list[str]) -> None:
    op.create_index(
        name,
        "observations",
        columns,
        sqlite_where=sa.text("sample_key IS NOT NULL"),
        postgresql_where=sa.text("sample_key IS NOT NULL"),
    )


def upgrade() -> None:
    with op.batch_alter_table("cameras") as batch:
        batch.add_column(_epoch_column())
        batch.add_column(sa.Column("epoch_reason", sa.String(32), nullable=True))
        batch.add_column(sa.Column("moved_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(sa.Column("moves", sa.Integer(), nullable=False, server_default=sa.text("0")))
        batch.create_check_constraint("epoch_positive", "epoch >= 1")
        batch.create_check_constraint("epoch_reason", f"epoch_reason IS NULL OR epoch_reason IN {EPOCH_REASONS}")
    op.add_column("observations", _epoch_column())
    op.add_column("calibrations", _epoch_column())
    op.drop_index(OLD_SAMPLING_INDEX, table_name="observations")
    _sampling_index(SAMPLING_INDEX, SAMPLING_COLUMNS)
    op.create_table(
        "movement_monitors",
        sa.Column("camera_id", sa.String(128), nullable=False),
        sa.Column("epoch", sa.Integer(), nullable=False),
        sa.Column("calibration_version", sa.Integer(), nullable=False),
        sa.Column("state", sa.LargeBinary(), nullable=False),
        sa.Column("statistic", sa.Double(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["camera_id"], ["cameras.id"], name="fk_movement_monitors_camera_id_cameras", ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("camera_id", name="pk_movement_monitors"),
    )


def downgrade() -> None:
    op.drop_table("movement_monitors")
    op.drop_index(SAMPLING_INDEX, table_name="observations")
    _sampling_index(OLD_SAMPLING_INDEX, OLD_SAMPLING_COLUMNS)
    with op.batch_alter_table("calibrations") as batch:
        batch.drop_column("epoch")
    with op.batch_alter_table("observations") as batch:
        batch.drop_column("epoch")
    with op.batch_alter_table("cameras") as batch:
        batch.drop_constraint("epoch_reason", type_="check")
        batch.drop_constraint("epoch_positive", type_="check")
        batch.drop_column("moves")
        batch.drop_column("moved_at")
        batch.drop_column("epoch_reason")
        batch.drop_column("epoch")
