"""How a worker shares itself between its queues: webhooks first, the others by their share of its time.

Real RQ and Redis; the jobs run in the worker process and advance a clock of the test's own, so the order the
worker chooses depends on the jobs' (simulated) durations and nothing else.
"""

from __future__ import annotations

from datetime import timedelta

import redis
from rq import Queue, SimpleWorker, get_current_job
from rq.utils import now

from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, POSE_QUEUE, QUEUES, WEBHOOKS_QUEUE
from workers.main import MAX_AGING, QUEUE_SHARES, WAIT_TARGET_S, _SharesTime

ORDER_KEY = "test:order"
_now = [0.0]


def work(name: str, seconds: float) -> None:
    """A job that takes `seconds` of the test's clock and records that it ran."""
    job = get_current_job()
    assert job is not None
    _now[0] += seconds
    job.connection.rpush(ORDER_KEY, name)


def frame_with_alert() -> None:
    """A frames job whose violation queues a webhook delivery."""
    job = get_current_job()
    assert job is not None
    Queue(WEBHOOKS_QUEUE, connection=job.connection).enqueue(work, "alert", 0.05)
    work("frames", 0.1)


class SharingWorker(_SharesTime, SimpleWorker):
    clock = staticmethod(lambda: _now[0])


def _served(worker_class: type[SimpleWorker], connection: redis.Redis) -> list[str]:
    queues = {name: Queue(name, connection=connection) for name in QUEUES}
    for index in range(40):  # a measuring backlog, as under load: frames jobs of 0.1 s
        if index == 20:
            queues[FRAMES_QUEUE].enqueue(frame_with_alert)
        queues[FRAMES_QUEUE].enqueue(work, "frames", 0.1)
    for _ in range(4):  # image frames (0.5 s each) and due solves (1 s each)
        queues[POSE_QUEUE].enqueue(work, "pose", 0.5)
        queues[CALIBRATION_QUEUE].enqueue(work, "calibration", 1.0)
    worker_class(list(queues.values()), connection=connection).work(burst=True)
    served = [item.decode() for item in connection.lrange(ORDER_KEY, 0, -1)]
    connection.delete(ORDER_KEY)
    return served


def _time_shares(served: list[str]) -> dict[str, float]:
    cost = {"frames": 0.1, "pose": 0.5, "calibration": 1.0, "alert": 0.05}
    return {kind: sum(cost[name] for name in served if name == kind) for kind in ("frames", "pose", "calibration")}


def test_pose_and_calibration_do_not_wait_behind_a_measuring_backlog(connection: redis.Redis) -> None:
    strict = _served(SimpleWorker, connection)  # RQ's order: every frames job before any pose job or solve
    assert strict.index("pose") == 42 and strict.index("calibration") == 46

    shared = _served(SharingWorker, connection)
    assert sorted(shared) == sorted(strict)  # the same work, in another order
    assert shared.index("pose") <= 2 and shared.index("calibration") <= 2  # each waits a job or two at most
    # The alert is queued by the 21st frames job and runs next, before anything else: webhooks stay first.
    frames_seen = [index for index, name in enumerate(shared) if name == "frames"]
    assert shared[frames_seen[20] + 1] == "alert"
    # While all three have work, each gets worker time in proportion to its share (2 : 2 : 1), to one job.
    busy = shared[: min(len(shared) - 1 - shared[::-1].index(kind) for kind in ("pose", "calibration"))]
    used = _time_shares(busy)
    total_share = sum(QUEUE_SHARES.values())
    for kind, queue in (("frames", FRAMES_QUEUE), ("pose", POSE_QUEUE), ("calibration", CALIBRATION_QUEUE)):
        assert abs(used[kind] - sum(used.values()) * QUEUE_SHARES[queue] / total_share) <= 1.0, used


def _solve_turn(worker_class: type[SharingWorker], connection: redis.Redis) -> int:
    """Where a solve comes in a measuring backlog when the calibration queue has lately had twice its share."""
    queues = {name: Queue(name, connection=connection) for name in (FRAMES_QUEUE, CALIBRATION_QUEUE)}
    for _ in range(6):
        queues[FRAMES_QUEUE].enqueue(work, "frames", 0.1)
    queues[CALIBRATION_QUEUE].enqueue(work, "calibration", 1.0)
    worker = worker_class(list(queues.values()), connection=connection)
    worker.used_s.update(
        {FRAMES_QUEUE: QUEUE_SHARES[FRAMES_QUEUE], CALIBRATION_QUEUE: 2 * QUEUE_SHARES[CALIBRATION_QUEUE]}
    )
    worker.work(burst=True)
    served = [item.decode() for item in connection.lrange(ORDER_KEY, 0, -1)]
    connection.delete(ORDER_KEY)
    return served.index("calibration")


def _seen_after(waited_s: float) -> type[SharingWorker]:
    class Later(SharingWorker):
        """The same worker, its jobs seen waited_s after they were queued."""

        wall_clock = staticmethod(lambda: now() + timedelta(seconds=waited_s))

    return Later


def test_a_solve_gets_a_larger_share_as_it_nears_its_target_wait_until_served(connection: redis.Redis) -> None:
    # A fresh solve waits its turn behind the measuring it is ahead of (its share is spent); one that has waited its
    # target (or longer) is served as soon as the job in hand is done (the first dequeue is RQ's order): its share
    # grew MAX_AGING x on the way there, so the target is not passed waiting for measuring.
    target_s = WAIT_TARGET_S[CALIBRATION_QUEUE]
    assert _solve_turn(SharingWorker, connection) == 6
    assert _solve_turn(_seen_after(target_s), connection) == 1
    assert _solve_turn(_seen_after(MAX_AGING * target_s), connection) == 1
