"""Frames in (keypoints, or images for the pose workers; stored, then dispatched), and their results out."""

from __future__ import annotations

import asyncio
import logging
import re
import uuid
from collections.abc import Mapping, Sequence
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request, Response, status
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import State

from service.calibration.service import DueSolves
from service.cameras.repository import CameraNotFoundError, CameraResizedError
from service.cameras.service import camera_not_found, require_camera
from service.dispatch import UNAVAILABLE_ERRORS, Dispatcher
from service.domain import CameraCounters
from service.frames import ingest, listing, repository
from service.frames.digests import image_frame_digest
from service.frames.images import ImageError, ImageTooLargeError, decode
from service.frames.schemas import (
    DetectedPersonOut,
    FrameAccepted,
    FrameList,
    FrameOut,
    FrameStatus,
    FrameSummary,
    KeypointFrame,
)
from service.frames.service import people_for_camera
from service.frames.uploads import OPENAPI_REQUEST_BODY, UPLOAD_TYPES, Upload, read_upload
from service.frames.writer import FrameNotStorableError, FrameWriter
from service.http.dependencies import CameraIdPath, DispatcherDep, ReadSessionDep, SettingsDep, queue_unavailable
from service.http.json_body import json_body, openapi_body
from service.http.links import frame_url
from service.http.problems import ProblemError, UploadRoute, problem_response_doc
from service.http.schemas import CLIENT_FRAME_ID_PATTERN, TimestampText
from service.observability.metrics import FRAMES_INGESTED
from service.observability.request_id import current_request_id
from service.settings import Settings
from service.store.models import Camera, Frame, Observation

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/cameras", tags=["frames"])
# Bodies read by json_body rather than declared in a signature; the app adds their schemas to its OpenAPI.
JSON_BODIES = (KeypointFrame,)


# How often a keypoint frame is checked again when its camera is resized while it is being stored.
RESIZE_RECHECKS = 2
CONFLICT_RESPONSE = {409: problem_response_doc("The frame_id is stored with other content (the body names that frame)")}


def frame_id_conflict(frame: Frame) -> ProblemError:
    """409 for a client frame id reused with other content: a retry must repeat the frame, and a new frame needs a
    new id; silently answering with the stored frame would drop the new content."""
    url = frame_url(frame.camera_id, frame.id)
    return ProblemError(
        409,
        "frame-id-conflict",
        f"Camera {frame.camera_id!r} already has a frame with frame_id {frame.client_frame_id!r} and other content "
        f"({url}). A retry must send the same timestamp and people (or image); give a new frame a new frame_id.",
        headers={"Location": url},
        frame_id=frame.id,
        client_frame_id=frame.client_frame_id,
        url=url,
    )


@router.post(
    "/{camera_id}/keypoints",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=FrameAccepted,
    responses={200: {"description": "A retry of a frame already stored (same client frame_id)"}, **CONFLICT_RESPONSE},
    openapi_extra=openapi_body(KeypointFrame),
)
async def post_keypoints(
    camera_id: CameraIdPath,
    body: Annotated[KeypointFrame, Depends(json_body(KeypointFrame))],
    request: Request,
    response: Response,
) -> FrameAccepted:
    """Store one frame's people, then nudge the workers: 202 with the frame's URL (200 for a retry).

    The measuring worker that picks the frame up also requests a calibration when the camera's evidence calls
    for one, so this hot path makes one call to the queue (per camera and write batch).

    Posting the same client `frame_id` again with the same content (README: Idempotency) returns the stored
    frame and stores nothing; if that frame is still pending it is dispatched again, which is how a client
    recovers from an earlier 503. The same `frame_id` with other content is 409. When the queue is unreachable
    the answer is 503, but the frame is already committed and workers pick it up on start.

    The camera comes from this process's memory; the store checks its image size again when it commits, and a
    frame whose camera was resized meanwhile is checked again against the new size (or refused), so a resize
    holds at once on every API process.
    """
    # Everything but the database and the queue runs on the event loop (the body was parsed there too); those two
    # are the frame writer's thread's, so a request crosses threads only there and back.
    state: State = request.app.state
    camera = state.camera_cache.cached(camera_id)
    writer: FrameWriter = state.frame_writer
    for _ in range(1 + RESIZE_RECHECKS):
        if camera is None:
            camera = await run_in_threadpool(state.camera_cache.get, camera_id)
            if camera is None:
                raise camera_not_found(camera_id)
        people = people_for_camera(body.people, camera, state.settings)
        new = ingest.NewKeypointFrame(
            camera, body.timestamp, people, client_frame_id=body.frame_id, request_id=current_request_id()
        )
        try:
            stored = await asyncio.wrap_future(writer.submit(new))
            break
        except CameraNotFoundError:
            state.camera_cache.forget(camera_id)
            raise camera_not_found(camera_id) from None  # deleted since it was read
        except CameraResizedError:
            state.camera_cache.forget(camera_id)  # read again, and the people checked against the new size
            camera = None
        except FrameNotStorableError as exc:
            raise ProblemError(422, "frame-not-storable", f"{str(exc)[0].upper()}{str(exc)[1:]}.") from exc
    else:
        raise ProblemError(
            409,
            "camera-changed",
            f"Camera {camera_id!r} was resized again and again while this frame was being stored; post it again.",
        )
    frame = stored.frame
    if not stored.created and frame.content_sha256 not in (None, new.content_sha256):
        raise frame_id_conflict(frame)
    if stored.created:
        FRAMES_INGESTED.labels(source="keypoints").inc()
    url = frame_url(camera_id, frame.id)
    if stored.after_commit_error is not None:
        raise queue_unavailable(
            "the frame is stored and will be processed when the queue is back.",
            stored.after_commit_error,
            frame_id=frame.id,
            url=url,
        ) from stored.after_commit_error
    return _accepted(frame, stored.created, url, response)


def dispatch_stored(
    dispatcher: Dispatcher,
    due_solves: DueSolves | None,
    stored: Sequence[tuple[Frame, bool]],
    counters: Mapping[str, CameraCounters] | None = None,
) -> list[BaseException | None]:
    """The frame writer's after-commit step: have the batch's new (or still pending) frames measured, with one
    call to the queue for the whole batch (one frame named per camera), and ask for the solves the new evidence
    made due (`counters`: the cameras' counters the batch's transaction left). If the queue is unreachable, each of
    those frames' posts is answered 503 (the frames are stored; the workers find them on start); a solve that could
    not be asked for is asked for again by the next batch."""
    waiting = [created or frame.status == "pending" for frame, created in stored]
    first_per_camera: dict[str, uuid.UUID] = {}
    for (frame, _), wanted in zip(stored, waiting, strict=True):
        if wanted:
            first_per_camera.setdefault(frame.camera_id, frame.id)
    failure: BaseException | None = None
    if first_per_camera:
        try:
            dispatcher.frames_stored(list(first_per_camera.items()))
        except UNAVAILABLE_ERRORS as exc:
            failure = exc
    new_evidence = {frame.camera_id for frame, created in stored if created}
    if due_solves is not None and new_evidence and failure is None:
        try:
            due_solves(new_evidence, counters)
        except (*UNAVAILABLE_ERRORS, SQLAlchemyError) as exc:
            log.warning("could not ask for the solves of %d cameras: %s", len(new_evidence), exc)
    return [failure if wanted else None for wanted in waiting]


# --------------------------------------------------------------------------------------------------- images

# Room for a multipart form's boundaries and small fields on top of the image itself.
MULTIPART_OVERHEAD_BYTES = 64 * 1024


def upload_route(settings: Settings) -> UploadRoute:
    """The image POST's body rules, for BodyGuard (which otherwise only lets JSON through)."""
    return UploadRoute(
        path=re.compile(r"/v1/cameras/[^/]+/frames"),
        max_body_bytes=settings.max_image_bytes + MULTIPART_OVERHEAD_BYTES,
        media_types=UPLOAD_TYPES,
        setting="max_image_bytes",
    )


@router.post(
    "/{camera_id}/frames",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=FrameAccepted,
    openapi_extra={"requestBody": OPENAPI_REQUEST_BODY},
    responses={200: {"description": "A retry of a frame already stored (same client frame_id)"}, **CONFLICT_RESPONSE},
)
async def post_image(
    camera_id: CameraIdPath,
    request: Request,
    response: Response,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
    timestamp: Annotated[
        TimestampText | None,
        Query(description="When the frame was taken (RFC 3339 with zone, or Unix seconds). Default: now."),
    ] = None,
    frame_id: Annotated[
        str | None,
        Query(pattern=CLIENT_FRAME_ID_PATTERN, description="The client's id: a retry with it is the same frame."),
    ] = None,
) -> FrameAccepted:
    """Store one JPEG or PNG frame (raw body, or multipart with an `image` file), then queue its pose job.

    The picture is checked here (type, size against the pixel budget before decoding, a complete decode, the
    camera's image size), so a bad image is a 4xx now rather than a failed frame later. It is kept only until
    its people are found, unless the camera keeps images. The frame is then read exactly like a keypoint frame.
    """
    upload = await read_upload(request, timestamp=timestamp, frame_id=frame_id)
    return await run_in_threadpool(_store_image, request, camera_id, upload, response, settings, dispatcher)


def _store_image(
    request: Request,
    camera_id: str,
    upload: Upload,
    response: Response,
    settings: Settings,
    dispatcher: Dispatcher,
) -> FrameAccepted:
    with request.app.state.read_session_factory() as session:
        camera = require_camera(session, camera_id)
    try:
        header, _image = decode(upload.data, max_pixels=settings.max_image_pixels)
    except ImageTooLargeError as exc:
        raise ProblemError(413, "image-too-large", f"{str(exc)[0].upper()}{str(exc)[1:]}.") from exc
    except ImageError as exc:
        raise ProblemError(422, "invalid-image", f"Invalid image: {exc}.") from exc
    if (header.width_px, header.height_px) != (camera.image_width_px, camera.image_height_px):
        raise _size_mismatch(camera_id, (header.width_px, header.height_px), camera_size(camera))
    digest = image_frame_digest(upload.data)
    with request.app.state.session_factory() as session:
        try:
            frame, created = ingest.add_image_frame(
                session,
                camera,
                timestamp=upload.timestamp,
                content_type=header.content_type,
                width_px=header.width_px,
                height_px=header.height_px,
                data=upload.data,
                client_frame_id=upload.frame_id,
                request_id=current_request_id(),
                content_sha256=digest,
            )
        except CameraNotFoundError:
            raise camera_not_found(camera_id) from None
        except CameraResizedError as exc:  # resized since it was read: the image is of the old size
            raise _size_mismatch(camera_id, (header.width_px, header.height_px), exc.size_px) from None
        session.commit()
    if not created and (
        frame.content_sha256 not in (None, digest) or (upload.timestamp_given and upload.timestamp != frame.timestamp)
    ):
        raise frame_id_conflict(frame)
    if created:
        FRAMES_INGESTED.labels(source="image").inc()
    url = frame_url(camera_id, frame.id)
    if created or frame.status == "detecting":
        try:
            dispatcher.image_stored(camera_id, frame.id)
        except UNAVAILABLE_ERRORS as exc:
            raise queue_unavailable(
                "the image is stored and will be processed when the queue is back.", exc, frame_id=frame.id, url=url
            ) from exc
    return _accepted(frame, created, url, response)


def camera_size(camera: Camera) -> tuple[int, int]:
    return camera.image_width_px, camera.image_height_px


def _size_mismatch(camera_id: str, image_px: tuple[int, int], camera_px: tuple[int, int]) -> ProblemError:
    return ProblemError(
        422,
        "image-size-mismatch",
        f"The image is {image_px[0]}x{image_px[1]} px, but camera {camera_id!r} is configured for "
        f"{camera_px[0]}x{camera_px[1]} px (a calibration holds for one image size).",
    )


def _accepted(frame: Frame, created: bool, url: str, response: Response) -> FrameAccepted:
    response.status_code = status.HTTP_202_ACCEPTED if created else status.HTTP_200_OK
    response.headers["Location"] = url
    return FrameAccepted(
        frame_id=frame.id,
        client_frame_id=frame.client_frame_id,
        status=frame.status,  # type: ignore[arg-type]
        people=frame.people,
        created=created,
        url=url,
    )


# --------------------------------------------------------------------------------------------------- reading


def _frame_fields(frame: Frame) -> dict[str, Any]:
    """What a frame's full answer and its list summary share, read from the stored row."""
    return {
        "frame_id": frame.id,
        "camera_id": frame.camera_id,
        "client_frame_id": frame.client_frame_id,
        "source": frame.source,
        "timestamp": frame.timestamp,
        "received_at": frame.received_at,
        "status": frame.status,
        "people": frame.people,
        "calibration_version": frame.calibration_version,
        "processed_at": frame.processed_at,
        "error": frame.error,
    }


def _links(url: str, image_kept: bool) -> dict[str, str]:
    links = {"topdown": f"{url}/topdown.png"}
    if image_kept:
        links["overlay"] = f"{url}/overlay.png"
    return links


def frame_json(
    frame: Frame, result_json: str | None, detections: list[DetectedPersonOut] | None, image_kept: bool
) -> str:
    """The frame as FrameOut's JSON, with its result spliced in as stored (the worker wrote it in FrameResult's
    shape): validating and re-encoding 190 pairs per poll cost three times as much as the rest of the answer."""
    links = _links(frame_url(frame.camera_id, frame.id), image_kept)
    envelope = FrameOut(
        **_frame_fields(frame),
        pose_model=frame.pose_model,
        detections=detections,
        image_kept=image_kept,
        links=links,
        result=None,
    ).model_dump_json(exclude={"result"})
    return f'{envelope[:-1]},"result":{result_json or "null"}}}'


@router.get("/{camera_id}/frames", response_model=FrameList)
def list_frames(
    camera_id: CameraIdPath,
    session: ReadSessionDep,
    status_: Annotated[FrameStatus | None, Query(alias="status", description="Only frames in this state.")] = None,
    since: Annotated[
        TimestampText | None, Query(description="Only frames taken at or after this time (the frame's timestamp).")
    ] = None,
    until: Annotated[TimestampText | None, Query(description="Only frames taken before this time.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Frames per page.")] = 50,
    before: Annotated[
        str | None,
        Query(min_length=1, max_length=200, description="The previous page's `next_before` (an opaque cursor)."),
    ] = None,
) -> FrameList:
    """The camera's frames, newest first by capture time, a page at a time, optionally of one status and within
    [since, until). Each item is a summary; its `url` has the people, distances and violations."""
    require_camera(session, camera_id)
    if since is not None and until is not None and since >= until:
        raise ProblemError(
            422, "invalid-window", f"`since` ({since.isoformat()}) must be before `until` ({until.isoformat()})."
        )
    try:
        position = None if before is None else listing.FramePosition.decode(before)
    except listing.BadCursorError:
        raise ProblemError(
            400, "bad-cursor", "`before` is not a cursor this API handed out: pass a page's `next_before` as it is."
        ) from None
    page = listing.list_frames(
        session, camera_id, limit=limit, before=position, status=status_, since=since, until=until
    )
    items = [_summary(listed) for listed in page]
    next_before = None
    if len(page) == limit:
        last = page[-1].frame
        next_before = listing.FramePosition(last.timestamp, last.id).encode()
    return FrameList(items=items, next_before=next_before)


def _summary(listed: listing.ListedFrame) -> FrameSummary:
    frame = listed.frame
    url = frame_url(frame.camera_id, frame.id)
    return FrameSummary(
        **_frame_fields(frame),
        violations=listed.violations,
        image_kept=listed.image_kept,
        url=url,
        links=_links(url, listed.image_kept),
    )


@router.get("/{camera_id}/frames/by-client-id/{client_frame_id}", response_model=FrameOut)
def get_frame_by_client_id(
    camera_id: CameraIdPath,
    client_frame_id: Annotated[
        str, Path(pattern=CLIENT_FRAME_ID_PATTERN, description="The `frame_id` the client posted the frame with.")
    ],
    session: ReadSessionDep,
) -> Response:
    """The frame the client posted with its own `frame_id`: the same answer as `GET .../frames/{frame_id}` (whose
    path takes only the service's UUIDs, so the two can never be confused)."""
    frame_id = listing.frame_id_by_client_id(session, camera_id, client_frame_id)
    if frame_id is None:
        require_camera(session, camera_id)
        raise ProblemError(
            404, "frame-not-found", f"Camera {camera_id!r} has no frame posted with frame_id {client_frame_id!r}."
        )
    return _frame_response(session, camera_id, frame_id)


@router.get("/{camera_id}/frames/{frame_id}", response_model=FrameOut)
def get_frame(
    camera_id: CameraIdPath,
    frame_id: Annotated[
        uuid.UUID,
        Path(
            description="The frame id (a UUID) the service answered the POST with. For the client's own `frame_id`, "
            "use `GET .../frames/by-client-id/{client_frame_id}`."
        ),
    ],
    session: ReadSessionDep,
) -> Response:
    """A frame's status and, once measured, its people's positions, pair distances and violations."""
    return _frame_response(session, camera_id, frame_id)


def _frame_response(session: Session, camera_id: str, frame_id: uuid.UUID) -> Response:
    found = repository.get_frame_with_encoded_result(session, camera_id, frame_id)
    if found is None:
        require_camera(session, camera_id)
        raise ProblemError(404, "frame-not-found", f"Camera {camera_id!r} has no frame {frame_id}.")
    frame, result_json = found
    detections, image_kept = None, False
    if frame.source == "image":
        if frame.status != "detecting":
            detections = [_detection_out(o) for o in repository.frame_observations(session, frame_id)]
        image_kept = repository.frame_image_kept(session, frame_id)
    return Response(frame_json(frame, result_json, detections, image_kept), media_type="application/json")


def _detection_out(person: Observation) -> DetectedPersonOut:
    shoulder, ankle = (person.shoulder_x_px, person.shoulder_y_px), (person.ankle_x_px, person.ankle_y_px)
    keypoints = person.keypoints
    return DetectedPersonOut(
        index=person.person_index,
        box_px=person.box_px,
        detection_score=person.detection_score,
        keypoints=None if keypoints is None else [(k[0], k[1], k[2]) for k in keypoints],
        shoulder_px=None if None in shoulder else shoulder,  # type: ignore[arg-type]
        ankle_px=None if None in ankle else ankle,  # type: ignore[arg-type]
        posture=person.posture,  # type: ignore[arg-type]
        usable=person.usable,
        unusable_reason=person.unusable_reason,
    )
