"""When the workers hand pending work to the queues again from SQL (the recovery pass, workers.main).

SQL holds every piece of work (frames pending or waiting for pose, calibrations due, webhook deliveries due);
Redis only holds the nudges. Nudges get lost: Redis restarted empty or from an old snapshot, a job that failed
because the database was down, a job that used up its retries. So besides a worker's start, the pass runs

- every RECOVERY_INTERVAL_S, on whichever worker's maintenance gets there first (`SCHEDULE_KEY`); a Redis that
  lost its data lost that key too, so a restarted Redis is re-filled at the next maintenance, within seconds;
- at the next maintenance after a job met an unavailable database (`request_recovery`), and again at each one
  after that while the pass itself fails, so work stalled by an outage resumes seconds after the database does.

One worker at a time runs it (`LOCK_KEY`). Requests are deduplicated per camera and pose or delivery jobs by id,
so a pass that finds everything under way queues nothing.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable

import redis

log = logging.getLogger(__name__)

RECOVERY_INTERVAL_S = 30
DUE_KEY = "posemetry:recovery:due"
SCHEDULE_KEY = "posemetry:recovery:scheduled"
LOCK_KEY = "posemetry:recovery:lock"
# Set by every full pass, without expiry: a Redis found without it lost its data since (restarted empty, or from an
# old snapshot), and with it every job it held, the scheduled webhook retries included. The next pass is then a
# full one, as at a worker's start: it queues every pending delivery, not only those overdue by a minute.
KEPT_KEY = "posemetry:recovery:kept"
# A pass that runs longer than this (a worker killed in the middle of one) no longer keeps the others out.
LOCK_TTL_S = 300
DUE_TTL_S = 24 * 3600
_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""
_REDIS_ERRORS = (redis.ConnectionError, redis.TimeoutError)


def request_recovery(connection: redis.Redis) -> None:
    """Ask for a recovery pass at the next maintenance of any worker (best effort: with Redis down there is nothing
    to recover into yet, and a Redis that comes back empty triggers the pass by itself)."""
    try:
        connection.set(DUE_KEY, "1", ex=DUE_TTL_S)
    except _REDIS_ERRORS as exc:
        log.warning("could not ask for a recovery pass: %s", exc)


def postpone_recovery(connection: redis.Redis) -> None:
    """A full pass just ran (a worker's start): the next periodic one is due RECOVERY_INTERVAL_S from now."""
    connection.set(SCHEDULE_KEY, "1", ex=RECOVERY_INTERVAL_S)
    connection.set(KEPT_KEY, "1")


class RecoverySchedule:
    """Runs `recover` when a pass is due (see the module docstring), or `recover_all` when Redis lost its data since
    the last full pass (KEPT_KEY); called from each worker's maintenance."""

    def __init__(
        self, connection: redis.Redis, recover: Callable[[], object], recover_all: Callable[[], object] | None = None
    ) -> None:
        self.connection = connection
        self.recover = recover
        self.recover_all = recover_all or recover
        self._release = connection.register_script(_RELEASE)

    def due(self) -> bool:
        return bool(self.connection.exists(DUE_KEY)) or bool(
            self.connection.set(SCHEDULE_KEY, "1", nx=True, ex=RECOVERY_INTERVAL_S)
        )

    def run_if_due(self) -> bool:
        """Run a pass if one is due and no other worker runs one; True when this call ran one that succeeded."""
        if not self.due():
            return False
        token = uuid.uuid4().hex
        if not self.connection.set(LOCK_KEY, token, nx=True, ex=LOCK_TTL_S):
            return False
        try:
            # Cleared first: a job that meets an outage while the pass runs asks for the next one.
            self.connection.delete(DUE_KEY)
            if self.connection.exists(KEPT_KEY):
                self.recover()
            else:
                self.recover_all()
                self.connection.set(KEPT_KEY, "1")
            return True
        except Exception:
            log.exception("recovery pass failed; the next maintenance tries again")
            request_recovery(self.connection)
            return False
        finally:
            self._release(keys=[LOCK_KEY], args=[token])
