"""A Redis that lost its data (restarted empty) gets a full recovery pass at the next maintenance, not the periodic
one: its scheduled webhook retries went with it, and the periodic pass leaves deliveries alone until they are a
minute overdue (their jobs are normally on their way). Found by tests/faults/test_faults_under_load.py: with the
workers still running, the last event reached the receiver 63 s after it came back; with this, seconds."""

from __future__ import annotations

import redis

from workers import recovery


def test_a_redis_that_lost_its_data_gets_a_full_pass_then_periodic_ones(connection: redis.Redis) -> None:
    runs: list[str] = []
    schedule = recovery.RecoverySchedule(connection, lambda: runs.append("periodic"), lambda: runs.append("full"))
    recovery.postpone_recovery(connection)  # a worker started: its own full pass ran
    assert not schedule.run_if_due()
    recovery.request_recovery(connection)
    assert schedule.run_if_due() and runs == ["periodic"]

    connection.flushall()  # restarted empty: no schedule, no marker
    assert schedule.run_if_due() and runs == ["periodic", "full"]
    recovery.request_recovery(connection)
    assert schedule.run_if_due() and runs == ["periodic", "full", "periodic"]


def test_a_failed_full_pass_stays_full(connection: redis.Redis) -> None:
    attempts: list[str] = []

    def full() -> None:
        attempts.append("full")
        if len(attempts) == 1:
            raise ConnectionError("database still down")

    schedule = recovery.RecoverySchedule(connection, lambda: attempts.append("periodic"), full)
    assert not schedule.run_if_due()
    assert not connection.exists(recovery.KEPT_KEY)
    assert schedule.run_if_due() and attempts == ["full", "full"]
    assert connection.exists(recovery.KEPT_KEY)
