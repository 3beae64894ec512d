"""The camera model users have (issue 16): camera settings for the principal point, fy, lens coefficients and the
camera's height; each calibration version keeps what measuring with it needs and what it is worth.

Every new column is nullable, so no data changes on upgrade: cameras keep assuming what they assumed, and a
version stored before this has no camera model (measured as before: no lens, ankles on the ground, keypoint
noise independent of a person's size) and no grade (it alerts as before).

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-25
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

CAMERA_COLUMNS = (
    ("known_focal_y_px", sa.Double()),
    ("principal_point_x_px", sa.Double()),
    ("principal_point_y_px", sa.Double()),
    ("distortion_coefficients", sa.JSON()),
    ("camera_height_m", sa.Double()),
    ("camera_height_tolerance_m", sa.Double()),
)
CAMERA_CHECKS = (
    ("known_focal_y_positive", "known_focal_y_px IS NULL OR known_focal_y_px > 0"),
    ("camera_height_positive", "camera_height_m IS NULL OR camera_height_m > 0"),
)
CALIBRATION_COLUMNS = (
    ("camera_model", sa.JSON()),
    ("quality_grade", sa.String(16)),
    ("quality", sa.JSON()),
)
GRADE_CHECK = ("quality_grade", "quality_grade IS NULL OR quality_grade IN ('good', 'rough', 'unreliable')")


def upgrade() -> None:
    with op.batch_alter_table("cameras") as batch:
        for name, kind in CAMERA_COLUMNS:
            batch.add_column(sa.Column(name, kind, nullable=True))
        for name, condition in CAMERA_CHECKS:
            batch.create_check_constraint(op.f(f"ck_cameras_{name}"), condition)
    with op.batch_alter_table("calibrations") as batch:
        for name, kind in CALIBRATION_COLUMNS:
            batch.add_column(sa.Column(name, kind, nullable=True))
        batch.create_check_constraint(op.f(f"ck_calibrations_{GRADE_CHECK[0]}"), GRADE_CHECK[1])


def downgrade() -> None:
    with op.batch_alter_table("calibrations") as batch:
        batch.drop_constraint(op.f(f"ck_calibrations_{GRADE_CHECK[0]}"), type_="check")
        for name, _ in reversed(CALIBRATION_COLUMNS):
            batch.drop_column(name)
    with op.batch_alter_table("cameras") as batch:
        for name, _ in reversed(CAMERA_CHECKS):
            batch.drop_constraint(op.f(f"ck_cameras_{name}"), type_="check")
        for name, _ in reversed(CAMERA_COLUMNS):
            batch.drop_column(name)
