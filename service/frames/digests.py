"""What "the same content" means for a client frame id (README, Idempotency): a frame's digest, stored with it.

A keypoint frame is the same when it has the same instant to the microsecond and the same people in the same order,
each as stored: keypoints at the float32 precision they are packed with, centres as float64, and the same track id
(a retry that calls a person by another track_id would link them to another individual: other content). How the
JSON spelled the numbers (1 or 1.0, 1e2 or 100) and the key order do not matter. An image frame is the same when
its bytes are.

A person without a track id adds nothing for it, so frames stored before track ids keep their digests.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta

from service.domain import PersonIn
from service.store.models import pack_keypoints

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_CENTRES = struct.Struct("<?dd?dd")


def _instant_bytes(timestamp: datetime) -> bytes:
    return ((timestamp - _EPOCH) // timedelta(microseconds=1)).to_bytes(8, "little", signed=True)


def keypoint_frame_digest(
    timestamp: datetime, people: Sequence[PersonIn], packed: Sequence[bytes | None] | None = None
) -> str:
    """SHA-256 (hex) of a keypoint frame's content; `packed` is each person's packed keypoints if already made."""
    digest = hashlib.sha256(b"posemetry keypoint frame v1\0")
    digest.update(_instant_bytes(timestamp))
    digest.update(len(people).to_bytes(4, "little"))
    for index, person in enumerate(people):
        if person.keypoints is not None:
            digest.update(b"k")
            digest.update(packed[index] if packed is not None else pack_keypoints(person.keypoints))  # type: ignore[arg-type]
        else:
            shoulder, ankle = person.shoulder_px, person.ankle_px
            digest.update(b"c")
            digest.update(
                _CENTRES.pack(
                    shoulder is not None,
                    *(shoulder or (0.0, 0.0)),
                    ankle is not None,
                    *(ankle or (0.0, 0.0)),
                )
            )
        if person.track_id is not None:
            # After the person's fixed-length points, and tagged: no other person's bytes can read as a track id.
            track = person.track_id.encode()
            digest.update(b"t" + len(track).to_bytes(1, "little") + track)
    return digest.hexdigest()


def image_frame_digest(data: bytes) -> str:
    """SHA-256 (hex) of an image frame's bytes. Its timestamp is compared apart, and only when a retry gives one:
    a frame posted without one is stamped with its time of receipt, which no retry can repeat."""
    return hashlib.sha256(b"posemetry image frame v1\0" + data).hexdigest()
