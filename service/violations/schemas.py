"""Bodies of the violation routes: counts per time bucket (the heat map is a PNG)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel


class ViolationBucketOut(BaseModel):
    start: datetime
    count: int


class ViolationCounts(BaseModel):
    """Violations per UTC-aligned time bucket in [since, until); empty buckets are omitted."""

    camera_id: str
    since: datetime
    until: datetime
    bucket: Literal["minute", "hour"]
    bucket_s: int
    total: int
    buckets: list[ViolationBucketOut]
