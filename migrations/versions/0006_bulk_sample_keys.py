"""Observations are stored unkeyed and keyed in bulk by the calibration job.

`sample_key` becomes nullable; the sampling index leaves unkeyed people out (a partial index), and an index on
(camera_id, sample_key, id) finds them in arrival order and takes over deletes by camera from the old sampling
index. Stored people keep their keys, so no data changes on upgrade; a downgrade keys the people still
unkeyed (with the service's key function) before the column is NOT NULL again.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

SAMPLING_INDEX = "ix_observations_camera_id_usable_cell_sample_key"
SAMPLING_COLUMNS = ["camera_id", "usable", "cell", "sample_key"]
BY_CAMERA_INDEX = "ix_observations_camera_id_sample_key_id"


def upgrade() -> None:
    op.drop_index(SAMPLING_INDEX, table_name="observations")
    with op.batch_alter_table("observations") as batch:
        batch.alter_column("sample_key", existing_type=sa.Integer(), nullable=True)
    op.create_index(BY_CAMERA_INDEX, "observations", ["camera_id", "sample_key", "id"])
    op.create_index(
        SAMPLING_INDEX,
        "observations",
        SAMPLING_COLUMNS,
        sqlite_where=sa.text("sample_key IS NOT NULL"),
        postgresql_where=sa.text("sample_key IS NOT NULL"),
    )


def downgrade() -> None:
    # The service's key (service.calibration.evidence.sample_key), frozen here: a migration must not change when
    # the service does.
    op.execute(
        "UPDATE observations SET sample_key = ((id % 2147483648) * 2654435761) % 2147483648 WHERE sample_key IS NULL"
    )
    op.drop_index(SAMPLING_INDEX, table_name="observations")
    op.drop_index(BY_CAMERA_INDEX, table_name="observations")
    with op.batch_alter_table("observations") as batch:
        batch.alter_column("sample_key", existing_type=sa.Integer(), nullable=False)
    op.create_index(SAMPLING_INDEX, "observations", SAMPLING_COLUMNS)
