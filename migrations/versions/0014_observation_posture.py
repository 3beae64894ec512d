"""observations.posture, placed_from_box and static: what measuring reads of the verdict on a person, kept as values
instead of the beginnings of `unusable_reason`.

Measuring placed a seated person from their shoulders at a seated height, a person whose pose was not read from
their detector box's bottom with that cue's sigma, and kept a static one (a mannequin) out of violations by
reading how the reason began. A static person placed from their box had a reason of 202 characters, longer than
the column, which PostgreSQL refuses. Upgrade fills the new columns from the reasons (the sentences as
service.frames.keypoints wrote them; written out here, so that upgrading imports none of the service); posture is
known for seated, partial and usable image people and for posted people with shoulders and no ankles (`partial`),
NULL for the others stored before. Downgrade drops the columns:
the earlier code then measures a static person placed from their box as placed from their ankles (a narrower sigma).

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-29
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014"
down_revision: str | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

SEATED = "seated or crouching (legs seen but folded)%"
PARTIAL = "lower body not seen (hidden or out of view)%"
BOX = "pose not read: placed from the detector box's bottom%"
STATIC = "static: found at a spot where nothing has moved for a long time (a mannequin, a poster, a statue)"


def upgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.add_column(sa.Column("posture", sa.String(8), nullable=True))
        batch.add_column(sa.Column("placed_from_box", sa.Boolean(), server_default=sa.text("false"), nullable=False))
        batch.add_column(sa.Column("static", sa.Boolean(), server_default=sa.text("false"), nullable=False))
    reason = sa.column("unusable_reason", sa.String)
    observations = sa.table(
        "observations",
        reason,
        sa.column("posture", sa.String),
        sa.column("placed_from_box", sa.Boolean),
        sa.column("static", sa.Boolean),
        sa.column("usable", sa.Boolean),
        sa.column("box_left_px", sa.Float),
        sa.column("shoulder_x_px", sa.Float),
        sa.column("ankle_x_px", sa.Float),
    )
    c = observations.c
    op.execute(observations.update().where(reason.like(SEATED)).values(posture="seated"))
    op.execute(observations.update().where(reason.like(PARTIAL)).values(posture="partial"))
    op.execute(observations.update().where(c.usable, c.box_left_px.is_not(None)).values(posture="standing"))
    # A posted person whose shoulders came without ankles: nobody can tell standing from seated.
    op.execute(
        observations.update()
        .where(c.box_left_px.is_(None), c.shoulder_x_px.is_not(None), c.ankle_x_px.is_(None))
        .values(posture="partial")
    )
    op.execute(
        observations.update().where(reason.like(BOX) | reason.like(f"{STATIC}; {BOX}")).values(placed_from_box=True)
    )
    op.execute(observations.update().where(reason.like(f"{STATIC}%")).values(static=True))


def downgrade() -> None:
    with op.batch_alter_table("observations") as batch:
        batch.drop_column("static")
        batch.drop_column("placed_from_box")
        batch.drop_column("posture")
