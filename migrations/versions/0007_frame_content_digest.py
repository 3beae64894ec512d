"""frames.content_sha256: a digest of what the client posted, so a client frame id reused with other content is a
409 conflict instead of a silent retry.

Nullable: frames stored before this revision have no digest; a post that reuses one of their client ids is
answered as a retry, as before. No data changes on upgrade or downgrade.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("frames") as batch:
        batch.add_column(sa.Column("content_sha256", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("frames") as batch:
        batch.drop_column("content_sha256")
