"""Job queues on Redis (RQ): the connection, the per-camera job gates, and the Redis dispatcher.

The API and the workers only ever talk to each other through Redis, and the service never imports `workers`:
jobs are enqueued by dotted function path, so the API process does not load the geometry to enqueue a frame.

Two kinds of work, two queues, both deduplicated per camera by a small state machine in Redis (`CameraGate`):
never two jobs of one kind for one camera at once and never a pile-up of queued ones; a request that arrives
while a job runs schedules exactly one re-run, because the running job may have read the camera's state before
the change that prompted the request.

- `frames`: measure a camera's pending frames. One job answers every frame that is pending when it runs, a
  chunk at a time, so under load frames are measured in batches (one read and one write transaction per chunk
  instead of per frame) and an idle camera's frame is answered as soon as a worker is free. Measuring is
  idempotent (a recomputed frame overwrites its result and replaces its violation events).
- `calibration`: solves.
- `webhooks`: one job per attempt of a webhook delivery (`webhook-<delivery uuid>-<attempt>`), due now or at a
  time (retries wait in RQ's scheduled-job registry, which workers serving this queue run a scheduler for). The
  delivery's state is in SQL and an attempt is claimed there before it is sent, so a job queued twice sends once.
- `pose`: one job per image frame (pose inference, the expensive step), with a deterministic job id
  (`pose-<frame uuid>`) so re-enqueueing every image frame still waiting (a worker restarting) never queues one
  twice. Pose jobs store their people only while the frame is still `detecting`, so a duplicate run is harmless.

A worker can die in the middle of a job (kill -9, out of memory, its machine lost). The process running a job
therefore renews its claims every JOB_HEARTBEAT_S (workers.liveness): its execution in RQ's StartedJobRegistry
and, for a gated job, its camera's running slot, each for JOB_LIVENESS_TTL_S. A dead job holds neither for
longer than that: RQ's registry maintenance, which the workers run every few seconds, puts it back on its queue
under the same id (`retry=Retry(max=JOB_RETRIES)`), and the camera's slot, which names that id, lets it in again.
"""

from __future__ import annotations

import hashlib
import time
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, NoReturn

import redis
from redis.backoff import ExponentialBackoff
from redis.exceptions import NoScriptError
from redis.retry import Retry as ConnectionRetry
from rq import Queue, Retry
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job, JobStatus
from rq.queue import EnqueueData
from rq.registry import ScheduledJobRegistry

from service.dispatch import DispatchUnavailableError
from service.embedded_redis import embedded_socket_path
from service.observability.request_id import JOB_META_KEY, current_request_id

if TYPE_CHECKING:
    from service.settings import Settings

FRAMES_QUEUE = "frames"
CALIBRATION_QUEUE = "calibration"
POSE_QUEUE = "pose"
WEBHOOKS_QUEUE = "webhooks"
# A worker takes webhooks first: an alert is what the user waits for, and a delivery is one short HTTP request;
# behind the frames queue (never empty while cameras post faster than the workers measure) alerts waited up to a
# minute under `posemetry bench load`. The other queues share the worker's time (workers.main._SharesTime): served
# in this order, pose and solves starved behind measuring.
QUEUES = (WEBHOOKS_QUEUE, FRAMES_QUEUE, POSE_QUEUE, CALIBRATION_QUEUE)

# Jobs are named by dotted path: the service must not import the workers package (it pulls in the geometry).
MEASURE_FRAMES_JOB = "workers.jobs.measure_frames"
CALIBRATE_CAMERA_JOB = "workers.jobs.calibrate_camera"
DETECT_PEOPLE_JOB = "workers.jobs.detect_people"
DELIVER_WEBHOOK_JOB = "workers.webhooks.deliver_webhook"

FRAMES_JOB_TIMEOUT_S = 120
CALIBRATION_JOB_TIMEOUT_S = 600
POSE_JOB_TIMEOUT_S = 300
# Far above the longest request a delivery may make (settings.webhook_timeout_s is at most 60 s per phase).
WEBHOOK_JOB_TIMEOUT_S = 300
# A queued job's claim on its camera lasts while the job may wait in its queue (the same claim is renewed by the
# next request after that); a running job's lasts JOB_LIVENESS_TTL_S and is renewed while its process lives.
FRAMES_QUEUED_TTL_S = FRAMES_JOB_TIMEOUT_S + 60
CALIBRATION_QUEUED_TTL_S = CALIBRATION_JOB_TIMEOUT_S + 120
# The process running a job renews its claims this often, each for JOB_LIVENESS_TTL_S (five missed beats): a
# job whose process died is taken for dead that long after its last beat, and retried.
JOB_HEARTBEAT_S = 2
JOB_LIVENESS_TTL_S = 10
# Retries of a job whose process died, or that raised (a database blip). A job that kills its worker every time
# (a poison input) fails for good after JOB_RETRIES + 1 runs.
JOB_RETRIES = 2
# Successful jobs leave nothing behind (results live in SQL); failed ones stay a week for inspection.
FAILED_JOB_TTL_S = 7 * 24 * 3600

_REDIS_ERRORS = (redis.ConnectionError, redis.TimeoutError)
# Redis refusing writes: full (maxmemory reached under noeviction), a replica (READONLY), or unable to persist its
# snapshot (MISCONF, with stop-writes-on-bgsave-error). The queues are as unavailable as with Redis down. Inside
# a Lua script the refusal comes back wrapped in the script's error, hence the search in the message.
_WRITE_REFUSALS = ("OOM", "READONLY", "MISCONF")
_WAITING = frozenset({JobStatus.QUEUED, JobStatus.DEFERRED, JobStatus.SCHEDULED})
# A started job is seen through by RQ too: to the end, or, if its process dies, retried by registry maintenance.
_UNDER_WAY = _WAITING | {JobStatus.STARTED}
_JOBS = {
    FRAMES_QUEUE: (MEASURE_FRAMES_JOB, FRAMES_JOB_TIMEOUT_S),
    CALIBRATION_QUEUE: (CALIBRATE_CAMERA_JOB, CALIBRATION_JOB_TIMEOUT_S),
}


# --------------------------------------------------------------------------------------------------- connection


def redis_url(settings: Settings) -> str:
    """The configured Redis URL, else the embedded Redis's socket in data_dir (`posemetry serve` runs one there)."""
    if settings.redis_url:
        return settings.redis_url
    return f"unix://{embedded_socket_path(settings.data_dir)}"


def connect(url: str, *, timeout_s: float = 5.0) -> redis.Redis:
    """A client for the queues. Bytes, not decoded strings: RQ stores pickled job payloads.

    The timeouts and the short retry schedule (two retries within about a second, rather than redis-py's default
    of backing off up to 10 s) ride out a blip but keep a dead Redis a fast 503 for the API, not a hung request.
    """
    return redis.Redis.from_url(
        url,
        socket_timeout=timeout_s,
        socket_connect_timeout=timeout_s,
        retry=ConnectionRetry(ExponentialBackoff(cap=0.5, base=0.05), 2),
    )


# --------------------------------------------------------------------------------------------------- camera gate

# The per-camera state of one kind of job lives in one key, `lock`, whose value is `queued:<job id>` or
# `running:<job id>`, plus three flags: `rerun` (a request came while a job ran), `forced` (a forced request waits
# for the next run) and `forcedrun` (the running job was forced: kept until a run of it completes, so a forced
# solve whose process died is still forced when it is retried). Each transition is a Lua script, so it is atomic
# across processes. KEYS: lock, rerun, forced, forcedrun.
_REQUEST = """
local state = redis.call('GET', KEYS[1])
if ARGV[3] == '1' then redis.call('SET', KEYS[3], '1', 'EX', ARGV[2]) end
if not state then
  redis.call('SET', KEYS[1], 'queued:' .. ARGV[1], 'EX', ARGV[2])
  redis.call('DEL', KEYS[2])
  return 1
end
if string.sub(state, 1, 8) == 'running:' then
  redis.call('SET', KEYS[2], '1', 'EX', ARGV[2])
  return 2
end
return 0
"""
_START = """
local state = redis.call('GET', KEYS[1])
if state and string.sub(state, 1, 8) == 'running:' and state ~= 'running:' .. ARGV[1] then
  redis.call('SET', KEYS[2], '1', 'EX', ARGV[2])
  return {0, 0}
end
redis.call('SET', KEYS[1], 'running:' .. ARGV[1], 'EX', ARGV[3])
redis.call('DEL', KEYS[2])
local forced = redis.call('GET', KEYS[3]) or redis.call('GET', KEYS[4])
redis.call('DEL', KEYS[3])
if forced then
  redis.call('SET', KEYS[4], '1', 'EX', ARGV[2])
  return {1, 1}
end
return {1, 0}
"""
_FINISH = """
if redis.call('GET', KEYS[1]) ~= 'running:' .. ARGV[1] then return 0 end
if ARGV[4] == '1' then redis.call('DEL', KEYS[4]) end
if redis.call('GET', KEYS[2]) then
  redis.call('DEL', KEYS[2])
  redis.call('SET', KEYS[1], 'queued:' .. ARGV[2], 'EX', ARGV[3])
  return 1
end
redis.call('DEL', KEYS[1])
return 0
"""
_RELEASE_LOST = """
if redis.call('GET', KEYS[1]) ~= 'queued:' .. ARGV[1] then return 0 end
return redis.call('DEL', KEYS[1])
"""
_REFRESH = """
if redis.call('GET', KEYS[1]) ~= 'running:' .. ARGV[1] then return 0 end
redis.call('EXPIRE', KEYS[1], ARGV[2])
return 1
"""


class RequestOutcome:
    """What a request did (for logs and tests)."""

    ALREADY_QUEUED = 0
    ENQUEUED = 1
    RERUN_SCHEDULED = 2


@dataclass(frozen=True)
class Ticket:
    """A job's right to run: `run` False means another job of its kind runs for the camera (a re-run is due)."""

    run: bool
    forced: bool


class CameraGate:
    """Per-camera deduplication of one kind of job (`kind`: "frames" or "calibration").

    States of a camera: idle (no key), queued (one job waits), running (one job works). A request when idle
    enqueues a job; when queued it does nothing (the waiting job will see the new data anyway); when running
    it sets the re-run flag, because the running job may have read before that data arrived. When a job
    finishes, a set flag turns into exactly one new queued job, however many requests set it. A forced
    request also sets a `forced` flag that the next job to start takes over, and that only a completed run of
    that job clears, so forcing is never lost to dedup nor to a dead worker.

    The running state lasts `running_ttl_s` and is renewed by the job's heartbeat (`refresh`), so a job whose
    process died frees its camera within seconds. A job may start again under its own id (RQ retrying it after
    its process died): the slot is still its own.
    """

    def __init__(
        self, connection: redis.Redis, kind: str, *, queued_ttl_s: int, running_ttl_s: int = JOB_LIVENESS_TTL_S
    ) -> None:
        self.connection = connection
        self.kind = kind
        self.queued_ttl_s = queued_ttl_s
        self.running_ttl_s = running_ttl_s
        self._request = connection.register_script(_REQUEST)
        self._start = connection.register_script(_START)
        self._finish = connection.register_script(_FINISH)
        self._refresh = connection.register_script(_REFRESH)
        self._release_lost = connection.register_script(_RELEASE_LOST)

    def keys(self, camera_id: str) -> list[str]:
        prefix = f"posemetry:{self.kind}:{camera_id}"
        return [f"{prefix}:lock", f"{prefix}:rerun", f"{prefix}:forced", f"{prefix}:forcedrun"]

    def request(self, camera_id: str, job_id: str, *, forced: bool = False) -> int:
        """Register a request; returns a RequestOutcome (ENQUEUED: the caller must now enqueue `job_id`)."""
        args = [job_id, self.queued_ttl_s, "1" if forced else "0"]
        return int(self._request(keys=self.keys(camera_id), args=args))

    def request_many(self, requests: Sequence[tuple[str, str]]) -> list[int]:
        """Register unforced requests, (camera id, job id) each, in one round trip; one RequestOutcome each.

        Each request is still its own atomic script; only the round trips are shared, which is what a batch of
        frames from many cameras costs: every wait for Redis is a wait for the API's GIL afterwards.

        A pipeline checks that its scripts are loaded once, before it sends; a Redis that restarts in between
        (the batch is retried on the new one) has none, and answers NOSCRIPT: those requests are made again one
        by one, which loads the script. Only those: the others ran, and asking twice would lose their grant."""
        pipe = self.connection.pipeline(transaction=False)
        for camera_id, job_id in requests:
            self._request(keys=self.keys(camera_id), args=[job_id, self.queued_ttl_s, "0"], client=pipe)
        outcomes = pipe.execute(raise_on_error=False)
        for k, outcome in enumerate(outcomes):
            if isinstance(outcome, NoScriptError):
                camera_id, job_id = requests[k]
                outcomes[k] = self._request(keys=self.keys(camera_id), args=[job_id, self.queued_ttl_s, "0"])
            elif isinstance(outcome, Exception):
                raise outcome
        return [int(outcome) for outcome in outcomes]

    def start(self, camera_id: str, job_id: str) -> Ticket:
        """Called by the job before it works: take the camera's running slot, and learn whether it was forced."""
        run, forced = self._start(keys=self.keys(camera_id), args=[job_id, self.queued_ttl_s, self.running_ttl_s])
        return Ticket(run=bool(run), forced=bool(forced))

    def refresh(self, camera_id: str, job_id: str) -> bool:
        """The running job's heartbeat: renew its slot (False if it lost the slot)."""
        return bool(self._refresh(keys=self.keys(camera_id), args=[job_id, self.running_ttl_s]))

    def finish(self, camera_id: str, job_id: str, next_job_id: str, *, completed: bool = True) -> bool:
        """Called by the job when done (or failed): True when a re-run is due as `next_job_id` (enqueue it).

        A run that did not complete (it raised) leaves a forced request standing for its retry or the next run.
        """
        args = [job_id, next_job_id, self.queued_ttl_s, "1" if completed else "0"]
        return bool(self._finish(keys=self.keys(camera_id), args=args))

    def queued_claims(self, camera_ids: Sequence[str]) -> list[tuple[str, str]]:
        """(camera id, job id) of each camera whose slot a queued job holds (one round trip)."""
        if not camera_ids:
            return []
        locks = self.connection.mget([self.keys(camera_id)[0] for camera_id in camera_ids])
        return [
            (camera_id, lock.decode()[len("queued:") :])
            for camera_id, lock in zip(camera_ids, locks, strict=True)
            if lock is not None and lock.startswith(b"queued:")
        ]

    def release_lost(self, camera_id: str, job_id: str) -> bool:
        """Free the camera's slot if `job_id` still holds it as queued (the caller found that job lost)."""
        return bool(self._release_lost(keys=self.keys(camera_id), args=[job_id]))

    def forced_outstanding(self, camera_ids: Sequence[str]) -> list[str]:
        """The cameras with a forced request not yet completed (one round trip): the recovery pass asks for their
        job again, in case the job that was to complete it failed (say, the database was down) or was lost."""
        if not camera_ids:
            return []
        keys = [key for camera_id in camera_ids for key in self.keys(camera_id)[2:4]]
        flags = self.connection.mget(keys)
        return [camera_id for k, camera_id in enumerate(camera_ids) if flags[2 * k] or flags[2 * k + 1]]

    def state(self, camera_id: str) -> str:
        """`idle`, `queued` or `running`."""
        value = self.connection.get(self.keys(camera_id)[0])
        if value is None:
            return "idle"
        return value.decode().split(":", 1)[0]


# --------------------------------------------------------------------------------------------------- dispatcher


def pose_job_id(frame_id: uuid.UUID | str) -> str:
    """RQ job ids allow only letters, digits, '-' and '_', which a UUID satisfies."""
    return f"pose-{frame_id}"


def webhook_job_id(delivery_id: uuid.UUID | str, attempt: int) -> str:
    """One id per attempt: a running attempt schedules the next one, which must not share its id (RQ deletes a
    finished job's id, and the scheduled one with it)."""
    return f"webhook-{delivery_id}-{attempt}"


def _job_status(connection: redis.Redis, job_id: str) -> JobStatus | None:
    try:
        return Job.fetch(job_id, connection=connection).get_status()
    except (NoSuchJobError, InvalidJobOperation):
        # Gone, or finished and deleted (result_ttl=0) between the fetch and the status read: no job waits.
        return None


def _raise_unavailable(exc: redis.RedisError) -> NoReturn:
    """Re-raise a Redis error as DispatchUnavailableError (a 503 for the API, a retry later for the workers) when
    Redis is away or refuses writes; any other error (a bug) as it is."""
    message = str(exc)
    refused = isinstance(exc, redis.exceptions.OutOfMemoryError | redis.exceptions.ReadOnlyError) or any(
        message.startswith(f"{code} ") or f"-{code} " in message for code in _WRITE_REFUSALS
    )
    if isinstance(exc, _REDIS_ERRORS) or refused:
        raise DispatchUnavailableError(f"job queue unavailable: {exc}") from exc
    raise exc


def _waits(status: bytes | None, queue_position: int | None) -> bool:
    """Whether a job will run without being asked again: waiting in its queue, scheduled or deferred, or started
    (RQ retries a started job whose process died)."""
    if status is None:
        return False
    if JobStatus(status.decode()) == JobStatus.QUEUED:
        return queue_position is not None
    return JobStatus(status.decode()) in _UNDER_WAY


def new_job_id(kind: str, camera_id: str) -> str:
    """Unique per job: a finished job's id must not collide with the re-run it schedules.

    Camera ids may hold characters RQ refuses in job ids, so the camera appears as a short hash.
    """
    camera_hash = hashlib.blake2b(camera_id.encode(), digest_size=8).hexdigest()
    return f"{kind}-{camera_hash}-{uuid.uuid4().hex}"


class RedisDispatcher:
    """The Dispatcher the API and the workers use: hands work to RQ, raising DispatchUnavailableError if Redis is down.

    Callers store first and dispatch second, so when Redis is down nothing accepted is lost: the frame stays
    pending in SQL and the workers enqueue it again when they start.
    """

    def __init__(self, connection: redis.Redis) -> None:
        self.connection = connection
        self.queues = {
            FRAMES_QUEUE: Queue(FRAMES_QUEUE, connection=connection),
            CALIBRATION_QUEUE: Queue(CALIBRATION_QUEUE, connection=connection),
            POSE_QUEUE: Queue(POSE_QUEUE, connection=connection),
            WEBHOOKS_QUEUE: Queue(WEBHOOKS_QUEUE, connection=connection),
        }
        self.gates = {
            FRAMES_QUEUE: CameraGate(connection, FRAMES_QUEUE, queued_ttl_s=FRAMES_QUEUED_TTL_S),
            CALIBRATION_QUEUE: CameraGate(connection, CALIBRATION_QUEUE, queued_ttl_s=CALIBRATION_QUEUED_TTL_S),
        }

    @classmethod
    def from_settings(cls, settings: Settings) -> RedisDispatcher:
        return cls(connect(redis_url(settings)))

    def frames_stored(self, frames: Sequence[tuple[str, uuid.UUID]]) -> None:
        """Have the cameras' pending frames measured (these among them); deduplicated per camera."""
        self.measure_requested(camera_id for camera_id, _ in frames)

    def measure_requested(self, camera_ids: Iterable[str]) -> int:
        """Ask for the pending frames of each camera to be measured, in two round trips at most (the gates, then
        the jobs they granted); returns how many jobs were queued."""
        cameras = list(dict.fromkeys(camera_ids))
        if not cameras:
            return 0
        job_ids = [new_job_id(FRAMES_QUEUE, camera_id) for camera_id in cameras]
        try:
            outcomes = self.gates[FRAMES_QUEUE].request_many(list(zip(cameras, job_ids, strict=True)))
            granted = [
                (camera_id, job_id)
                for camera_id, job_id, outcome in zip(cameras, job_ids, outcomes, strict=True)
                if outcome == RequestOutcome.ENQUEUED
            ]
            if granted:
                self.queues[FRAMES_QUEUE].enqueue_many([self._job_data(FRAMES_QUEUE, *job) for job in granted])
        except redis.RedisError as exc:
            _raise_unavailable(exc)
        return len(granted)

    def image_stored(self, camera_id: str, frame_id: uuid.UUID) -> None:
        """Queue the image frame's pose job unless one is already waiting for it."""
        self.images_pending([(camera_id, frame_id)])

    def images_pending(self, frames: Iterable[tuple[str, uuid.UUID]]) -> int:
        """Queue pose jobs for (camera_id, frame_id) pairs; returns how many were actually queued."""
        queued = 0
        # One request posts one image: the pose job carries its id (the worker logs under it).
        request_id = current_request_id()
        meta = None if request_id is None else {JOB_META_KEY: request_id}
        try:
            for camera_id, frame_id in frames:
                job_id = pose_job_id(frame_id)
                if _job_status(self.connection, job_id) in _UNDER_WAY:
                    continue
                self.queues[POSE_QUEUE].enqueue(
                    DETECT_PEOPLE_JOB,
                    str(frame_id),
                    job_id=job_id,
                    description=f"pose of frame {frame_id} of camera {camera_id}",
                    job_timeout=POSE_JOB_TIMEOUT_S,
                    result_ttl=0,
                    failure_ttl=FAILED_JOB_TTL_S,
                    retry=Retry(max=JOB_RETRIES),
                    meta=meta,
                )
                queued += 1
        except redis.RedisError as exc:
            _raise_unavailable(exc)
        return queued

    def deliveries_due(self, due: Iterable[tuple[uuid.UUID, int, datetime | None]]) -> int:
        """Queue attempt `n` of each delivery, now or at its time (a time in the past means now); returns how many
        were queued. One already queued to run is left alone; one scheduled is moved to the time given, since the
        caller has the newer word on when it is due (an attempt that just failed, a subscription re-enabled)."""
        queued = 0
        queue = self.queues[WEBHOOKS_QUEUE]
        scheduled = ScheduledJobRegistry(queue=queue)
        try:
            for delivery_id, attempt, at in due:
                job_id = webhook_job_id(delivery_id, attempt)
                status = _job_status(self.connection, job_id)
                if status == JobStatus.SCHEDULED:
                    scheduled.remove(job_id)
                elif status in _WAITING:
                    continue
                options: dict[str, Any] = {
                    "job_id": job_id,
                    "description": f"webhook delivery {delivery_id}, attempt {attempt}",
                    "job_timeout": WEBHOOK_JOB_TIMEOUT_S,
                    "result_ttl": 0,
                    "failure_ttl": FAILED_JOB_TTL_S,
                }
                if at is None or at <= datetime.now(UTC):
                    queue.enqueue(DELIVER_WEBHOOK_JOB, str(delivery_id), attempt, **options)
                else:
                    queue.enqueue_at(at, DELIVER_WEBHOOK_JOB, str(delivery_id), attempt, **options)
                queued += 1
        except redis.RedisError as exc:
            _raise_unavailable(exc)
        return queued

    def calibration_requested(self, camera_id: str, forced: bool) -> None:
        """Ask for a solve of the camera; deduplicated per camera."""
        try:
            self.request(CALIBRATION_QUEUE, camera_id, forced=forced)
        except redis.RedisError as exc:
            _raise_unavailable(exc)

    def request(self, kind: str, camera_id: str, *, forced: bool = False) -> int:
        """A gated request for a job of `kind` (a queue name) on the camera; returns the RequestOutcome."""
        job_id = new_job_id(kind, camera_id)
        outcome = self.gates[kind].request(camera_id, job_id, forced=forced)
        if outcome == RequestOutcome.ENQUEUED:
            self.enqueue(kind, camera_id, job_id)
        return outcome

    def enqueue(self, kind: str, camera_id: str, job_id: str) -> None:
        """Queue a job whose slot the gate already granted (a new request, or a re-run a finished job owes)."""
        self.queues[kind].enqueue_many([self._job_data(kind, camera_id, job_id)])

    @staticmethod
    def _job_data(kind: str, camera_id: str, job_id: str) -> EnqueueData:
        function, timeout_s = _JOBS[kind]
        return Queue.prepare_data(
            function,
            (camera_id,),
            job_id=job_id,
            description=f"{kind} of camera {camera_id}",
            timeout=timeout_s,
            result_ttl=0,
            failure_ttl=FAILED_JOB_TTL_S,
            retry=Retry(max=JOB_RETRIES),
        )

    def state(self, kind: str, camera_id: str) -> str:
        """`idle`, `queued` or `running` (the calibration status endpoint reports the latter two as calibrating)."""
        try:
            return self.gates[kind].state(camera_id)
        except redis.RedisError as exc:
            _raise_unavailable(exc)

    def calibration_state(self, camera_id: str) -> str:
        return self.state(CALIBRATION_QUEUE, camera_id)

    def release_lost_claims(self, kind: str, camera_ids: Sequence[str]) -> int:
        """Free each camera slot held by a queued job of `kind` that waits nowhere; returns how many were freed.

        A claim outlives its job when the job never reached its queue (the API or a worker died between the gate
        and the enqueue) or when a worker died between taking the job off the queue and RQ marking it started:
        RQ's registry cleanup skips a job that is not `started`, so nothing would run it, and every request would
        find the camera queued until the claim expires (FRAMES_QUEUED_TTL_S: three minutes of frames left
        pending). The recovery pass frees such slots before asking again. A job caught in flight between the
        queue and its start is taken for lost too; its second run is one more gated run, which the gate makes
        harmless (see CameraGate).
        """
        try:
            claims = self.gates[kind].queued_claims(camera_ids)
            if not claims:
                return 0
            queue_key = self.queues[kind].key
            pipe = self.connection.pipeline(transaction=False)
            for _, job_id in claims:
                pipe.hget(Job.key_for(job_id), "status")
                pipe.lpos(queue_key, job_id)
            answers = pipe.execute()
            released = 0
            for k, (camera_id, job_id) in enumerate(claims):
                status, position = answers[2 * k], answers[2 * k + 1]
                if not _waits(status, position):
                    released += self.gates[kind].release_lost(camera_id, job_id)
            return released
        except redis.RedisError as exc:
            _raise_unavailable(exc)

    def forced_calibrations(self, camera_ids: Sequence[str]) -> list[str]:
        """The cameras whose forced solve is still to be completed (see CameraGate.forced_outstanding)."""
        try:
            return self.gates[CALIBRATION_QUEUE].forced_outstanding(camera_ids)
        except redis.RedisError as exc:
            _raise_unavailable(exc)

    def ready(self) -> bool:
        """Whether Redis answers (for /readyz)."""
        try:
            return bool(self.connection.ping())
        except (redis.RedisError, OSError):
            return False


def wait_for_redis(connection: redis.Redis, *, timeout_s: float) -> None:
    """Block until Redis answers or the timeout passes (processes started together race the server's start)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            connection.ping()
            return
        except _REDIS_ERRORS:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.1)
