"""Initial schema: cameras, frames, observations, calibrations, violation_events.

Written to match service/store/models.py at the time (tests/store/test_migrations.py checks that autogenerate
finds no difference). Constraint expressions are frozen here as literals: later model changes need a new
revision, not an edit of this one.

Revision ID: 0001
Revises:
Create Date: 2026-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "cameras",
        sa.Column("id", sa.String(length=128), nullable=False),
        sa.Column("image_width_px", sa.Integer(), nullable=False),
        sa.Column("image_height_px", sa.Integer(), nullable=False),
        sa.Column("person_height_m", sa.Double(), nullable=False),
        sa.Column("equal_focal", sa.Boolean(), nullable=False),
        sa.Column("distance_threshold_m", sa.Double(), nullable=False),
        sa.Column("known_focal_px", sa.Double(), nullable=True),
        sa.Column("usable_evidence_count", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.Column("evidence_at_last_solve", sa.BigInteger(), server_default=sa.text("0"), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("distance_threshold_m > 0", name=op.f("ck_cameras_distance_threshold_positive")),
        sa.CheckConstraint("image_width_px > 0 AND image_height_px > 0", name=op.f("ck_cameras_image_size_positive")),
        sa.CheckConstraint(
            "known_focal_px IS NULL OR known_focal_px > 0", name=op.f("ck_cameras_known_focal_positive")
        ),
        sa.CheckConstraint("person_height_m > 0", name=op.f("ck_cameras_person_height_positive")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_cameras")),
    )
    op.create_table(
        "calibrations",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("camera_id", sa.String(length=128), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("reason", sa.Text(), nullable=True),
        sa.Column("fx_px", sa.Double(), nullable=True),
        sa.Column("fy_px", sa.Double(), nullable=True),
        sa.Column("cx_px", sa.Double(), nullable=True),
        sa.Column("cy_px", sa.Double(), nullable=True),
        sa.Column("normal_x", sa.Double(), nullable=True),
        sa.Column("normal_y", sa.Double(), nullable=True),
        sa.Column("normal_z", sa.Double(), nullable=True),
        sa.Column("rho_m", sa.Double(), nullable=True),
        sa.Column("fx_std_px", sa.Double(), nullable=True),
        sa.Column("fy_std_px", sa.Double(), nullable=True),
        sa.Column("normal_std_deg", sa.Double(), nullable=True),
        sa.Column("rho_std_m", sa.Double(), nullable=True),
        sa.Column("covariance", sa.JSON(), nullable=True),
        sa.Column("noise_px", sa.Double(), nullable=True),
        sa.Column("distortion_k", sa.Double(), nullable=True),
        sa.Column("person_height_m", sa.Double(), nullable=False),
        sa.Column("people_used", sa.Integer(), nullable=False),
        sa.Column("inliers", sa.Integer(), nullable=False),
        sa.Column("evidence_count", sa.BigInteger(), nullable=False),
        sa.Column("is_current", sa.Boolean(), nullable=False),
        sa.Column("forced", sa.Boolean(), nullable=False),
        sa.Column("duration_s", sa.Double(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("NOT is_current OR status = 'ok'", name=op.f("ck_calibrations_current_is_ok")),
        sa.CheckConstraint(
            "status <> 'ok' OR (fx_px IS NOT NULL AND fy_px IS NOT NULL AND cx_px IS NOT NULL AND cy_px IS NOT NULL "
            "AND normal_x IS NOT NULL AND normal_y IS NOT NULL AND normal_z IS NOT NULL AND rho_m IS NOT NULL)",
            name=op.f("ck_calibrations_ok_is_complete"),
        ),
        sa.CheckConstraint("status IN ('ok', 'failed')", name=op.f("ck_calibrations_status")),
        sa.CheckConstraint("version >= 1", name=op.f("ck_calibrations_version_positive")),
        sa.ForeignKeyConstraint(
            ["camera_id"], ["cameras.id"], name=op.f("fk_calibrations_camera_id_cameras"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_calibrations")),
        sa.UniqueConstraint("camera_id", "version", name=op.f("uq_calibrations_camera_id_version")),
    )
    op.create_index(
        "uq_calibrations_camera_id_current",
        "calibrations",
        ["camera_id"],
        unique=True,
        sqlite_where=sa.text("is_current"),
        postgresql_where=sa.text("is_current"),
    )
    op.create_table(
        "frames",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("camera_id", sa.String(length=128), nullable=False),
        sa.Column("client_frame_id", sa.String(length=128), nullable=True),
        sa.Column("timestamp", sa.DateTime(timezone=True), nullable=False),
        sa.Column("received_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("people", sa.Integer(), nullable=False),
        sa.Column("result", sa.JSON(), nullable=True),
        sa.Column("calibration_version", sa.Integer(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("processed_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint("source IN ('keypoints', 'image')", name=op.f("ck_frames_source")),
        sa.CheckConstraint("status IN ('pending', 'done', 'failed')", name=op.f("ck_frames_status")),
        sa.CheckConstraint("people >= 0", name=op.f("ck_frames_people_non_negative")),
        sa.ForeignKeyConstraint(
            ["camera_id"], ["cameras.id"], name=op.f("fk_frames_camera_id_cameras"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_frames")),
        sa.UniqueConstraint("camera_id", "client_frame_id", name=op.f("uq_frames_camera_id_client_frame_id")),
    )
    op.create_index(
        "ix_frames_status_camera_id_received_at", "frames", ["status", "camera_id", "received_at"], unique=False
    )
    op.create_table(
        "observations",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), autoincrement=True, nullable=False),
        sa.Column("camera_id", sa.String(length=128), nullable=False),
        sa.Column("frame_id", sa.Uuid(), nullable=False),
        sa.Column("person_index", sa.Integer(), nullable=False),
        sa.Column("shoulder_x_px", sa.Double(), nullable=True),
        sa.Column("shoulder_y_px", sa.Double(), nullable=True),
        sa.Column("ankle_x_px", sa.Double(), nullable=True),
        sa.Column("ankle_y_px", sa.Double(), nullable=True),
        sa.Column("keypoints", sa.JSON(), nullable=True),
        sa.Column("usable", sa.Boolean(), nullable=False),
        sa.Column("unusable_reason", sa.String(length=200), nullable=True),
        sa.Column("cell", sa.Integer(), nullable=True),
        sa.Column("sample_key", sa.Integer(), nullable=False),
        sa.CheckConstraint(
            "NOT usable OR (shoulder_x_px IS NOT NULL AND shoulder_y_px IS NOT NULL AND ankle_x_px IS NOT NULL "
            "AND ankle_y_px IS NOT NULL AND cell IS NOT NULL)",
            name=op.f("ck_observations_usable_is_complete"),
        ),
        sa.CheckConstraint("cell IS NULL OR (cell >= 0 AND cell < 64)", name=op.f("ck_observations_cell_on_grid")),
        sa.CheckConstraint(
            "sample_key >= 0 AND sample_key < 2147483648", name=op.f("ck_observations_sample_key_range")
        ),
        sa.CheckConstraint("usable OR unusable_reason IS NOT NULL", name=op.f("ck_observations_unusable_has_reason")),
        sa.ForeignKeyConstraint(
            ["camera_id"], ["cameras.id"], name=op.f("fk_observations_camera_id_cameras"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["frame_id"], ["frames.id"], name=op.f("fk_observations_frame_id_frames"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_observations")),
        sa.UniqueConstraint("frame_id", "person_index", name=op.f("uq_observations_frame_id_person_index")),
    )
    op.create_index(
        "ix_observations_camera_id_usable_cell_sample_key",
        "observations",
        ["camera_id", "usable", "cell", "sample_key"],
        unique=False,
    )
    op.create_table(
        "violation_events",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), autoincrement=True, nullable=False),
        sa.Column("camera_id", sa.String(length=128), nullable=False),
        sa.Column("frame_id", sa.Uuid(), nullable=False),
        sa.Column("timestamp", sa.DateTime(timezone=True), nullable=False),
        sa.Column("epoch_s", sa.BigInteger(), nullable=False),
        sa.Column("person_i", sa.Integer(), nullable=False),
        sa.Column("person_j", sa.Integer(), nullable=False),
        sa.Column("distance_m", sa.Double(), nullable=False),
        sa.Column("distance_std_m", sa.Double(), nullable=True),
        sa.CheckConstraint("person_i < person_j", name=op.f("ck_violation_events_pair_ordered")),
        sa.ForeignKeyConstraint(
            ["camera_id"], ["cameras.id"], name=op.f("fk_violation_events_camera_id_cameras"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["frame_id"], ["frames.id"], name=op.f("fk_violation_events_frame_id_frames"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_violation_events")),
        sa.UniqueConstraint(
            "frame_id", "person_i", "person_j", name=op.f("uq_violation_events_frame_id_person_i_person_j")
        ),
    )
    op.create_index("ix_violation_events_camera_id_epoch_s", "violation_events", ["camera_id", "epoch_s"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_violation_events_camera_id_epoch_s", table_name="violation_events")
    op.drop_table("violation_events")
    op.drop_index("ix_observations_camera_id_usable_cell_sample_key", table_name="observations")
    op.drop_table("observations")
    op.drop_index("ix_frames_status_camera_id_received_at", table_name="frames")
    op.drop_table("frames")
    op.drop_index("uq_calibrations_camera_id_current", table_name="calibrations")
    op.drop_table("calibrations")
    op.drop_table("cameras")
