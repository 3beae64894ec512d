"""Frame ids: time-ordered UUIDv7 drawn without a system call (ingest.new_frame_id)."""

from __future__ import annotations

import multiprocessing
import os
import random
import time
import uuid

import pytest

from service.frames.ingest import new_frame_id


def test_a_frame_id_is_a_version_7_uuid_of_the_current_millisecond() -> None:
    before_ms = time.time_ns() // 1_000_000
    frame_id = new_frame_id()
    after_ms = time.time_ns() // 1_000_000
    assert type(frame_id) is uuid.UUID  # a plain UUID: ids are pickled into jobs
    assert frame_id.version == 7 and frame_id.variant == uuid.RFC_4122
    assert before_ms <= frame_id.int >> 80 <= after_ms


def test_frame_ids_are_unique_and_ordered_by_their_millisecond() -> None:
    ids = [new_frame_id() for _ in range(100_000)]
    assert len(set(ids)) == len(ids)
    assert [i.int >> 80 for i in ids] == sorted(i.int >> 80 for i in ids)
    time.sleep(0.002)
    assert new_frame_id() > max(ids)


def test_a_frame_id_reads_no_os_randomness(monkeypatch: pytest.MonkeyPatch) -> None:
    """os.urandom releases the GIL, and the frame writer's thread then waits for the event loop to hand it back."""

    def refuse(*_args: object) -> bytes:
        raise AssertionError("the OS's randomness was read")

    monkeypatch.setattr(os, "urandom", refuse)
    monkeypatch.setattr(random, "_urandom", refuse)  # what secrets and random.SystemRandom read
    assert new_frame_id().version == 7


def _ids_in_child(queue: multiprocessing.Queue) -> None:
    queue.put([new_frame_id() for _ in range(1000)])


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_process_draws_other_ids_than_its_parent() -> None:
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_ids_in_child, args=(queue,))
    child.start()
    theirs = queue.get(timeout=30)
    child.join(timeout=30)
    ours = [new_frame_id() for _ in range(1000)]
    assert not {i.int & (2**62 - 1) for i in theirs} & {i.int & (2**62 - 1) for i in ours}
