"""Mixed load on `posemetry serve`: `posemetry bench load` (a script that prints figures, not a test).

What runs, on loopback, for a measured window (60 s by default) after a warm-up:

- **Cameras posting keypoints**: 50 cameras, each its own simulated scene (bench.simulate's
  surveillance preset: its own mounting height, tilt and field of view) with 20 people walking through it
  (bench.frames), each posting COCO-17 frames at 6 frames/s: 300 frames/s in all, the issue's target.
- **Cameras posting images**: a few cameras posting real Oxford Town Centre JPEGs (1920x1080) at a low rate; the
  pose workers find the people with the real ONNX models.
- **Dashboards** polling every camera's calibration status, **distance queries** (`POST .../distances`, keypoints
  in, metres out, synchronously) and **frame results** (`GET .../frames/{id}`: one keypoint frame in N and every
  image frame is followed until `done`, which also gives the time from POST to result).
- **Prometheus** scraping `/metrics`, which also gives queue depths and what the workers' jobs took, by queue.
- **A webhook subscription** for a couple of cameras, delivered to a local receiver that checks each signature
  and times each alert from the frame's POST to its arrival (a couple of cameras only: one subscription per
  camera at this violation rate would be a webhook benchmark, not a picture of mixed load).

**Open loop.** Every client sends on a fixed schedule (cameras do not slow down because the server does), each on
its own keep-alive connection, one request at a time as a camera gateway would. A closed loop (send the next
request when the last is answered) would hide the server's slowness by sending less (coordinated omission).
Latency is measured from the send; how late a request left its schedule (its connection still busy, or the
client itself behind) is measured apart, and the keypoint table also gives the latency from the schedule.

**The client is measured too.** It is one process with one event loop (uvloop), pre-encoded bodies and a lean
HTTP client (bench.http_client); its CPU time, and that of every other process on the machine, is
reported next to the server's, so a reader can tell a slow server from a starved one.

Against another deployment (`--url`), the same load runs without the per-process CPU split (and, without
`--database-url`, without the database backlog).
"""

from __future__ import annotations

import asyncio
import json
import math
import random
import secrets
import tempfile
import time
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from pathlib import Path

import psutil

from .frames import WalkingCamera, walking_cameras
from .http_client import Connection, Response, serve
from .load_calibration import CalibrationWatch, solve_times
from .load_options import (
    BACKLOG_EVERY_S,
    EXPECTED_STATUS,
    FOLLOW_MAX_POLL_S,
    GET_CALIBRATION,
    GET_FRAME,
    GET_METRICS,
    IMAGE_SIZE_PX,
    KINDS,
    LOOP_PROBE_S,
    MAX_SEND_LAG_S,
    POST_DISTANCES,
    POST_IMAGE,
    POST_KEYPOINTS,
    TRANSPORT_ERRORS,
    WEBHOOK_PATH,
    LoadOptions,
    LoadResult,
    Target,
    WebhookCounts,
    check_models,
    read_images,
    target_for,
)
from .load_stats import BacklogSample, CpuSnapshot, Followed, KindStats, cpu_split, load_average
from .metrics_text import MetricSample, delta_by, jobs_by_queue, labelled, parse_metrics
from .profile import Profiler, ProfileSummary
from .server import WORKERS, create_cameras, process_counts

Progress = Callable[[str], None]

# --------------------------------------------------------------------------------------------------- the run


class LoadRun:
    """The clients, the samplers and the bookkeeping of one run, on one event loop."""

    def __init__(self, options: LoadOptions, target: Target, walks: list[WalkingCamera], images: list[bytes]) -> None:
        self.options = options
        self.target = target
        self.walks = walks
        self.images = images
        self.rng = random.Random(options.seed)
        run = secrets.token_hex(2)
        self.keypoint_ids = [f"load-{run}-kp{index:02d}" for index in range(options.keypoint_cameras)]
        self.image_ids = [f"load-{run}-img{index}" for index in range(options.image_cameras)]
        self.kinds = {kind: KindStats(EXPECTED_STATUS.get(kind, 200)) for kind in KINDS}
        self.keypoints_done = Followed()
        self.images_done = Followed()
        self.followed: dict[tuple[str, str], tuple[float, bool]] = {}  # (camera, frame id) -> (sent wall, image?)
        self.backlog: list[BacklogSample] = []  # t_s in loop time until the run ends, then from the window's start
        self.queue_depths: list[tuple[float, dict[str, float]]] = []
        self.metrics_at_start: dict[MetricSample, float] = {}
        self.webhooks = WebhookCounts() if options.webhook_cameras else None
        self._webhook_ids: set[str] = set()
        self._webhook_secret = ""
        self.frames_posted = [0] * options.keypoint_cameras
        self.loop_lag_s: list[float] = []
        self.calibrations = CalibrationWatch()
        # The measured window, in loop time: empty and open-ended until the warm-up is over.
        self.t0 = math.inf
        self.t1 = math.inf
        self.wall_t0 = math.inf

    # ------------------------------------------------------------------ bookkeeping

    def in_window(self, scheduled: float) -> bool:
        return self.t0 <= scheduled < self.t1

    def _connection(self, token: str | None = None) -> Connection:
        return Connection(self.target.host, self.target.port, token=token or self.target.token)

    async def _send(
        self,
        kind: str,
        connection: Connection,
        scheduled: float,
        method: str,
        path: str,
        body: bytes | None = None,
        content_type: bytes = b"application/json",
    ) -> Response | None:
        """One request, recorded under `kind` when its schedule falls in the window; None when it got no answer."""
        loop = asyncio.get_running_loop()
        sent = loop.time()
        try:
            response = await connection.request(method, path, body, content_type)
        except TRANSPORT_ERRORS as exc:
            if self.in_window(scheduled):
                reason = "timeout" if isinstance(exc, TimeoutError) else type(exc).__name__
                self.kinds[kind].record_failure(sent - scheduled, loop.time() - sent, reason)
            return None
        if self.in_window(scheduled):
            self.kinds[kind].record(sent - scheduled, loop.time() - sent, response.status)
        return response

    async def _every(
        self, kind: str, interval_s: float, phase_s: float, send: Callable[[float, int], Awaitable[None]]
    ) -> None:
        """`await send(scheduled, n)` on a fixed schedule (open loop) until the window closes.

        A call that overruns delays the next one (one request at a time per connection), which the next one's
        send lag shows. A client more than MAX_SEND_LAG_S behind skips the slots it missed, as a camera drops
        frames it cannot send: otherwise a server that fell behind once would be measured for minutes on a
        backlog of stale requests. Skipped slots in the window count as errors of `kind`.
        """
        loop = asyncio.get_running_loop()
        scheduled = loop.time() + phase_s
        n = 0
        while scheduled < self.t1:
            delay = scheduled - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif -delay > MAX_SEND_LAG_S:
                missed = math.ceil((-delay - MAX_SEND_LAG_S) / interval_s)
                skipped = [scheduled + i * interval_s for i in range(missed)]
                self.kinds[kind].skipped += sum(self.in_window(slot) for slot in skipped)
                scheduled += missed * interval_s
                n += missed
                continue
            await send(scheduled, n)
            scheduled += interval_s
            n += 1

    @staticmethod
    def _timestamp(wall: float) -> str:
        return datetime.fromtimestamp(wall, UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")

    # ------------------------------------------------------------------ clients

    async def keypoint_camera(self, index: int) -> None:
        camera_id, walk = self.keypoint_ids[index], self.walks[index]
        connection = self._connection()
        path = f"/v1/cameras/{camera_id}/keypoints"
        interval = 1.0 / self.options.keypoint_fps

        async def post(scheduled: float, n: int) -> None:
            sent_wall = time.time()
            body = b'{"timestamp":"%s","frame_id":"f%06d","people":%s}' % (
                self._timestamp(sent_wall).encode(),
                n,
                walk.frame(n),
            )
            response = await self._send(POST_KEYPOINTS, connection, scheduled, "POST", path, body)
            self.frames_posted[index] = n
            if response is not None and response.status == 202 and (n + index) % self.options.follow_every == 0:
                self._follow(camera_id, response, sent_wall, scheduled, image=False)

        await self._every(POST_KEYPOINTS, interval, self.rng.uniform(0, interval), post)
        connection.close()

    async def image_camera(self, index: int) -> None:
        camera_id = self.image_ids[index]
        connection = self._connection()
        interval = 1.0 / self.options.image_fps

        async def post(scheduled: float, n: int) -> None:
            sent_wall = time.time()
            path = f"/v1/cameras/{camera_id}/frames?frame_id=f{n:06d}&timestamp={self._timestamp(sent_wall)}"
            image = self.images[(n + index * 7) % len(self.images)]
            response = await self._send(POST_IMAGE, connection, scheduled, "POST", path, image, b"image/jpeg")
            if response is not None and response.status == 202:
                self._follow(camera_id, response, sent_wall, scheduled, image=True)

        await self._every(POST_IMAGE, interval, self.rng.uniform(0, interval), post)
        connection.close()

    def _follow(self, camera_id: str, response: Response, sent_wall: float, scheduled: float, *, image: bool) -> None:
        if self.in_window(scheduled):
            frame_id = json.loads(response.body)["frame_id"]
            self.followed[(camera_id, frame_id)] = (sent_wall, image)

    async def dashboard(self, index: int) -> None:
        """Polls the calibration status of every camera, round robin, at its share of the polling rate."""
        cameras = [*self.keypoint_ids, *self.image_ids]
        connection = self._connection()
        interval = self.options.dashboards / self.options.calibration_polls_per_s

        async def poll(scheduled: float, n: int) -> None:
            camera_id = cameras[(n * self.options.dashboards + index) % len(cameras)]
            path = f"/v1/cameras/{camera_id}/calibration"
            response = await self._send(GET_CALIBRATION, connection, scheduled, "GET", path)
            if response is not None and response.status == 200:
                self.calibrations.record(camera_id, time.time(), response.body)

        await self._every(GET_CALIBRATION, interval, self.rng.uniform(0, interval), poll)
        connection.close()

    async def distance_queries(self) -> None:
        """Keypoints in, metres out: a random camera's latest people, measured synchronously."""
        connection = self._connection()

        async def query(scheduled: float, _n: int) -> None:
            index = self.rng.randrange(len(self.keypoint_ids))
            body = b'{"people":%s}' % self.walks[index].frame(self.frames_posted[index])
            path = f"/v1/cameras/{self.keypoint_ids[index]}/distances"
            await self._send(POST_DISTANCES, connection, scheduled, "POST", path, body)

        await self._every(POST_DISTANCES, 1.0 / self.options.distance_queries_per_s, 0.0, query)
        connection.close()

    async def follow_frames(self, until: asyncio.Event) -> None:
        """GET each followed frame until it is done (or `until` is set): first `follow_poll_s` after it is seen,
        then at doubling intervals up to FOLLOW_MAX_POLL_S, as a client waiting for a result would. The time to
        `done` is the server's `processed_at` minus the client's send time, so the polling interval does not blur
        it. (Polling every followed frame every round made this a closed loop whose load grew with the server's
        speed: 53 GET/s, then 115 once the API answered faster, most of them for image frames waiting for pose.)"""
        connection = self._connection()
        loop = asyncio.get_running_loop()
        due: dict[tuple[str, str], tuple[float, float]] = {}  # followed frame -> (next poll, interval), loop time
        while not until.is_set():
            for key in list(self.followed):
                poll_at, interval = due.setdefault(key, (loop.time() + self.options.follow_poll_s, 0.0))
                if poll_at > loop.time():
                    continue
                camera_id, frame_id = key
                path = f"/v1/cameras/{camera_id}/frames/{frame_id}"
                response = await self._send(GET_FRAME, connection, loop.time(), "GET", path)
                frame = json.loads(response.body) if response is not None and response.status == 200 else None
                if frame is None or frame["status"] not in ("done", "failed"):
                    interval = min(2 * interval or self.options.follow_poll_s, FOLLOW_MAX_POLL_S)
                    due[key] = (loop.time() + interval, interval)
                    continue
                del due[key]
                sent_wall, image = self.followed.pop(key)
                followed = self.images_done if image else self.keypoints_done
                if frame["status"] == "failed":
                    followed.failed += 1
                else:
                    followed.done_s.append(datetime.fromisoformat(frame["processed_at"]).timestamp() - sent_wall)
            next_poll = min((poll_at for poll_at, _ in due.values()), default=loop.time() + self.options.follow_poll_s)
            try:
                await asyncio.wait_for(until.wait(), min(max(next_poll - loop.time(), 0.0), self.options.follow_poll_s))
            except TimeoutError:
                pass
        for _sent, image in self.followed.values():
            (self.images_done if image else self.keypoints_done).unfinished += 1
        connection.close()

    # ------------------------------------------------------------------ samplers

    async def scrape(self, connection: Connection, scheduled: float) -> dict[MetricSample, float] | None:
        """GET /metrics (recorded as a request kind like any other), keeping the queue depths it reports."""
        response = await self._send(GET_METRICS, connection, scheduled, "GET", "/metrics")
        if response is None or response.status != 200:
            return None
        samples = parse_metrics(response.body.decode())
        queued = {
            labels["queue"]: value
            for labels, value in labelled(samples, "posemetry_queue_jobs")
            if labels.get("state") == "queued"
        }
        self.queue_depths.append((scheduled - self.t0, queued))
        return samples

    async def prometheus(self) -> None:
        """Scrapes /metrics from the window's start, every `metrics_every_s`; the first scrape is the baseline."""
        connection = self._connection(self.target.admin_key)

        async def scrape(scheduled: float, n: int) -> None:
            samples = await self.scrape(connection, scheduled)
            if samples is not None and n == 0:
                self.metrics_at_start = samples

        await self._every(GET_METRICS, self.options.metrics_every_s, 0.0, scrape)
        connection.close()

    async def watch_loop(self) -> None:
        """How late the client's own event loop wakes up (a 10 ms sleep, over and over, through the window): a
        starved or saturated client shows here, whatever the server does."""
        loop = asyncio.get_running_loop()
        while loop.time() < self.t1:
            before = loop.time()
            await asyncio.sleep(LOOP_PROBE_S)
            if self.in_window(before):
                self.loop_lag_s.append(loop.time() - before - LOOP_PROBE_S)

    async def sample_backlog(self, until: asyncio.Event) -> None:
        if self.target.database_url is None:
            return
        from .backlog import BacklogReader

        reader = BacklogReader(self.target.database_url)
        loop = asyncio.get_running_loop()
        try:
            while not until.is_set():
                pending, detecting, oldest_age_s = await asyncio.to_thread(reader.read)
                self.backlog.append(BacklogSample(loop.time(), pending, detecting, oldest_age_s))
                try:
                    await asyncio.wait_for(until.wait(), BACKLOG_EVERY_S)
                except TimeoutError:
                    pass
        finally:
            reader.close()

    def caught_up(self, since: float) -> bool:
        """No followed frame is still waiting, and the database (where read) showed no backlog after `since`."""
        if self.followed:
            return False
        if self.target.database_url is None:
            return True
        last = self.backlog[-1] if self.backlog else None
        return last is not None and last.t_s >= since and last.pending + last.detecting == 0

    # ------------------------------------------------------------------ webhooks

    def webhook_received(self, _method: str, _path: str, headers: dict[str, str], body: bytes) -> tuple[int, bytes]:
        from service.webhooks.signing import signature

        assert self.webhooks is not None
        counts = self.webhooks
        counts.received += 1
        message_id = headers.get("webhook-id", "")
        expected = signature(self._webhook_secret, message_id, int(headers.get("webhook-timestamp", "0")), body)
        if expected not in headers.get("webhook-signature", "").split():
            counts.bad_signature += 1
        if message_id in self._webhook_ids:
            counts.duplicates += 1
        self._webhook_ids.add(message_id)
        event = json.loads(body)
        counts.by_type[event["type"]] = counts.by_type.get(event["type"], 0) + 1
        if event["type"] == "violation.detected":
            # The frame's timestamp is when the client posted it.
            posted = datetime.fromisoformat(event["data"]["frame"]["timestamp"]).timestamp()
            if posted >= self.wall_t0:
                counts.alert_s.append(time.time() - posted)
        return 204, b""

    async def subscribe_webhook(self) -> asyncio.Server | None:
        if self.webhooks is None:
            return None
        receiver = await serve(self.webhook_received)
        port = receiver.sockets[0].getsockname()[1]
        cameras = self.keypoint_ids[: self.options.webhook_cameras]
        body = {"url": f"http://127.0.0.1:{port}{WEBHOOK_PATH}", "camera_ids": cameras, "description": "bench load"}
        connection = self._connection(self.target.admin_key)
        response = await connection.request("POST", "/v1/webhooks", json.dumps(body).encode())
        connection.close()
        if response.status != 201:
            raise RuntimeError(f"POST /v1/webhooks answered {response.status}: {response.body[:300]!r}")
        self._webhook_secret = json.loads(response.body)["secret"]
        return receiver

    # ------------------------------------------------------------------ phases

    async def calibrated_cameras(self) -> int:
        """Keypoint cameras with a calibration (image cameras calibrate as fast as pose finds people: not waited
        for, but their frames' time to `done` shows it)."""
        connection = self._connection()
        calibrated = 0
        for camera_id in self.keypoint_ids:
            response = await connection.request("GET", f"/v1/cameras/{camera_id}/calibration")
            calibrated += response.status == 200 and json.loads(response.body)["status"] == "calibrated"
        connection.close()
        return calibrated

    async def solve_history(self) -> dict[str, list[float]]:
        """Every camera's solve times (bench.load_calibration), read after the drain."""
        connection = self._connection()
        solved_at = {}
        for camera_id in [*self.keypoint_ids, *self.image_ids]:
            response = await connection.request("GET", f"/v1/cameras/{camera_id}/calibration/history?limit=1000")
            solved_at[camera_id] = solve_times(response.body) if response.status == 200 else []
        connection.close()
        return solved_at

    async def _seed_camera(self, camera_id: str, bodies: list[tuple[str, bytes, bytes]]) -> None:
        connection = self._connection()
        for path, body, content_type in bodies:
            response = await connection.request("POST", path, body, content_type)
            if response.status not in (200, 202):
                raise RuntimeError(
                    f"seeding {camera_id}: POST {path} answered {response.status}: {response.body[:300]!r}"
                )
        connection.close()

    async def seed(self, progress: Progress) -> None:
        """Every camera's first frames, then a wait for every camera's first calibration: the window then sees a
        service in its steady state, not 50 new cameras at once (`seed_frames` 0 skips this: a cold start)."""
        options = self.options
        if options.seed_frames == 0:
            return
        stamp = self._timestamp(time.time())
        seeds = []
        for index, camera_id in enumerate(self.keypoint_ids):
            path = f"/v1/cameras/{camera_id}/keypoints"
            bodies = [
                (
                    path,
                    b'{"timestamp":"%s","frame_id":"s%d","people":%s}'
                    % (stamp.encode(), n, self.walks[index].frame(n)),
                    b"application/json",
                )
                for n in range(options.seed_frames)
            ]
            seeds.append(self._seed_camera(camera_id, bodies))
        for index, camera_id in enumerate(self.image_ids):
            bodies = [
                (
                    f"/v1/cameras/{camera_id}/frames?frame_id=s{n}&timestamp={stamp}",
                    self.images[(n + index * 7) % len(self.images)],
                    b"image/jpeg",
                )
                for n in range(options.seed_images)
            ]
            seeds.append(self._seed_camera(camera_id, bodies))
        progress(
            f"seeding: {options.seed_frames} frames per keypoint camera, {options.seed_images} images per image "
            "camera, then waiting for every camera's first calibration"
        )
        await asyncio.gather(*seeds)
        loop = asyncio.get_running_loop()
        started = loop.time()
        total = len(self.keypoint_ids)
        while await self.calibrated_cameras() < total and loop.time() - started < options.max_warmup_s:
            await asyncio.sleep(1.0)

    def _clients(self) -> list[asyncio.Task[None]]:
        options = self.options
        clients = [self.keypoint_camera(i) for i in range(options.keypoint_cameras)]
        clients += [self.image_camera(i) for i in range(options.image_cameras)]
        if options.calibration_polls_per_s > 0:
            clients += [self.dashboard(i) for i in range(options.dashboards)]
        if options.distance_queries_per_s > 0:
            clients.append(self.distance_queries())
        return [asyncio.create_task(client) for client in clients]

    async def _warm_up(self, progress: Progress) -> tuple[float, int]:
        """At least `warmup_s` of full load, then until every camera is calibrated (up to `max_warmup_s`)."""
        options = self.options
        loop = asyncio.get_running_loop()
        started = loop.time()
        progress(f"warm-up: {options.warmup_s:g} s of full load (longer if a camera is not calibrated yet)")
        await asyncio.sleep(options.warmup_s)
        total = len(self.keypoint_ids)
        calibrated = await self.calibrated_cameras()
        while calibrated < total and loop.time() - started < options.max_warmup_s:
            await asyncio.sleep(2.0)
            calibrated = await self.calibrated_cameras()
        return loop.time() - started, calibrated

    def _roles(self) -> dict[str, list[psutil.Process]]:
        return self.target.server.processes() if self.target.server is not None else {}

    async def run(self, progress: Progress) -> LoadResult:
        options = self.options
        loop = asyncio.get_running_loop()
        receiver = await self.subscribe_webhook()
        await self.seed(progress)
        stop_following, stop_sampling = asyncio.Event(), asyncio.Event()
        clients = self._clients()
        samplers = [
            asyncio.create_task(self.follow_frames(stop_following)),
            asyncio.create_task(self.sample_backlog(stop_sampling)),
        ]
        warmup_s, calibrated = await self._warm_up(progress)

        roles = self._roles()
        profiler = None
        if options.profile_dir is not None and roles:
            profiler = Profiler(options.profile_dir)
            profiler.start(roles, options.seconds)
        load_before = load_average()
        cpu_start = CpuSnapshot.take(roles)
        self.t0, self.wall_t0 = loop.time(), time.time()
        self.t1 = self.t0 + options.seconds
        total = len(self.keypoint_ids)
        progress(f"measuring for {options.seconds:g} s ({calibrated}/{total} cameras calibrated)")
        scraper = asyncio.create_task(self.prometheus())
        probe = asyncio.create_task(self.watch_loop())
        await asyncio.sleep(options.seconds)
        roles_after = self._roles()
        cpu_end = CpuSnapshot.take(roles_after)
        load_after = load_average()
        connection = self._connection(self.target.admin_key)
        metrics_at_end = await self.scrape(connection, loop.time()) or {}
        connection.close()

        progress(f"window over; waiting up to {options.drain_s:g} s for the workers to catch up")
        await asyncio.gather(*clients, scraper, probe)  # what is in flight
        caught_up_after_s = None
        while loop.time() - self.t1 < options.drain_s:
            if self.caught_up(since=self.t1):
                caught_up_after_s = loop.time() - self.t1
                break
            await asyncio.sleep(0.25)
        stop_following.set()
        stop_sampling.set()
        solved_at = await self.solve_history()
        freshness = self.calibrations.freshness(solved_at, (self.wall_t0, self.wall_t0 + options.seconds), time.time())
        await asyncio.gather(*samplers)
        if receiver is not None:
            receiver.close()
        profiles: dict[str, ProfileSummary] = {}
        if profiler is not None:
            profiles = await asyncio.to_thread(profiler.finish)
        for sample in self.backlog:
            sample.t_s -= self.t0
        worker_pids = {p.pid for p in roles.get(WORKERS, [])}
        return LoadResult(
            options=options,
            target=f"http://{self.target.host}:{self.target.port}",
            window_s=options.seconds,
            warmup_s=warmup_s,
            calibrated_at_start=calibrated,
            kinds=self.kinds,
            keypoints_done=self.keypoints_done,
            images_done=self.images_done,
            backlog=self.backlog,
            caught_up_after_s=caught_up_after_s,
            queue_depths=self.queue_depths,
            jobs=jobs_by_queue(self.metrics_at_start, metrics_at_end),
            webhook_outcomes=delta_by(
                self.metrics_at_start, metrics_at_end, "posemetry_webhook_deliveries_total", "outcome"
            ),
            cpu_s=cpu_split(cpu_start, cpu_end),
            load_before=load_before,
            load_after=load_after,
            webhooks=self.webhooks,
            profiles=profiles,
            profiler_cpu_s=profiler.cpu_s if profiler is not None else 0.0,
            client_loop_lag_s=self.loop_lag_s,
            worker_restarts=len({p.pid for p in roles_after.get(WORKERS, [])} - worker_pids),
            freshness=freshness,
        )


# --------------------------------------------------------------------------------------------------- entry


def run_load(options: LoadOptions, progress: Progress) -> LoadResult:
    """Start the server (unless --url), set up cameras, a key and a webhook, run the load, stop the server."""
    import uvloop

    model_dir = check_models(options) if options.image_cameras and options.url is None else None
    images = read_images(options)
    progress(
        f"simulating {options.keypoint_cameras} cameras x {options.frames_per_camera} frames of "
        f"{options.people} walking people"
    )
    camera_body, walks = walking_cameras(
        options.keypoint_cameras,
        options.seed,
        frames=options.frames_per_camera,
        fps=options.keypoint_fps,
        payload=options.payload,
        people=options.people,
    )
    with tempfile.TemporaryDirectory(prefix="posemetry-load-") as tmp:
        target = target_for(options, Path(tmp), model_dir)
        if target.server is not None:
            progress(
                f"starting posemetry serve ({process_counts(options.api_processes, options.workers)}) on "
                f"port {target.port}, data in {tmp}"
            )
            target.server.start()
        try:
            run = LoadRun(options, target, walks, images)
            image_body = {"image_width_px": IMAGE_SIZE_PX[0], "image_height_px": IMAGE_SIZE_PX[1]}
            cameras = {camera_id: camera_body for camera_id in run.keypoint_ids}
            cameras |= {camera_id: image_body for camera_id in run.image_ids}
            target.token = create_cameras(
                target.port, cameras, admin_key=target.admin_key, key_name="bench load", host=target.host
            )
            result = uvloop.run(run.run(progress))
        finally:
            if target.server is not None:
                target.server.stop()
    if result.worker_restarts:
        result.notes.append(f"{result.worker_restarts} worker processes were restarted during the window")
    return result
