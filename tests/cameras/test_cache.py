"""The API's per-process camera cache: reused within its time, refreshed behind the requests after it, forgotten on
change, absence never kept."""

from __future__ import annotations

import pytest
from sqlalchemy import Engine, update
from sqlalchemy.orm import Session, sessionmaker

from service.cameras.cache import CameraCache
from service.cameras.repository import delete_camera
from service.store import make_session_factory
from service.store.models import Camera
from tests.support.store import add_camera

pytestmark = pytest.mark.both_backends


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _with_camera(engine: Engine, camera_id: str) -> sessionmaker[Session]:
    sessions = make_session_factory(engine)
    with sessions() as session:
        add_camera(session, camera_id)
        session.commit()
    return sessions


def _resize(sessions: sessionmaker[Session], camera_id: str, width_px: int) -> None:
    """Another process's change: straight to the database, past the cache."""
    with sessions() as session, session.begin():
        session.execute(update(Camera).where(Camera.id == camera_id).values(image_width_px=width_px))


def test_a_camera_is_reused_until_its_time_is_up_then_refreshed_behind_the_requests(engine: Engine) -> None:
    sessions = _with_camera(engine, "cam-1")
    clock = Clock()
    cache = CameraCache(ttl_s=2.0, sessions=sessions, clock=clock)
    assert cache.cached("cam-1") is None  # `cached` never reads
    first = cache.get("cam-1")
    assert first is not None and cache.cached("cam-1") is first
    width = first.image_width_px
    _resize(sessions, "cam-1", width + 100)
    clock.now += 1.9
    cached = cache.get("cam-1")
    assert cached is first and cached.image_width_px == width  # still trusted
    clock.now += 0.2
    assert cache.cached("cam-1") is first  # stale: served as it is while a refresh reads it again
    cache.close()  # waits for the refresh
    fresh = cache.cached("cam-1")
    assert fresh is not None and fresh.image_width_px == width + 100  # read again after ttl_s
    _resize(sessions, "cam-1", width + 200)
    clock.now += 2.1
    assert cache.cached("cam-1") is None  # stale, and a closed cache refreshes nothing: the caller reads
    assert cache.get("cam-1").image_width_px == width + 200  # type: ignore[union-attr]


def test_an_entry_whose_refresh_failed_is_read_by_the_request_once_twice_too_old(engine: Engine) -> None:
    sessions = _with_camera(engine, "cam-1")
    clock = Clock()
    failing = False

    def flaky_sessions() -> Session:
        if failing:
            raise ConnectionError("database unreachable")
        return sessions()

    cache = CameraCache(ttl_s=2.0, sessions=flaky_sessions, clock=clock)
    first = cache.get("cam-1")
    failing = True  # the database goes away after the first read
    clock.now += 3.0
    assert cache.cached("cam-1") is first  # stale: served while the refresh (which fails) runs
    cache._refresher.submit(lambda: None).result()  # the refresh has run and failed
    assert cache.cached("cam-1") is first  # another refresh is tried meanwhile
    cache._refresher.submit(lambda: None).result()
    clock.now += 1.1  # past twice ttl_s: no longer served
    assert cache.cached("cam-1") is None
    failing = False
    assert cache.get("cam-1") is not None
    cache.close()


def test_a_refresh_that_read_before_a_forget_stores_nothing(engine: Engine) -> None:
    sessions = _with_camera(engine, "cam-1")

    def forgotten_meanwhile() -> Session:
        cache.forget("cam-1")  # this process changed the camera while the read was under way
        return sessions()

    cache = CameraCache(ttl_s=60.0, sessions=forgotten_meanwhile, clock=Clock())
    assert cache.get("cam-1") is not None
    assert cache.cached("cam-1") is None  # what it read may predate the change: not kept


def test_forget_and_a_zero_ttl_read_again(engine: Engine) -> None:
    sessions = _with_camera(engine, "cam-1")
    cache = CameraCache(ttl_s=60.0, sessions=sessions, clock=Clock())
    width = cache.get("cam-1").image_width_px  # type: ignore[union-attr]
    _resize(sessions, "cam-1", width + 1)
    cache.forget("cam-1")  # what the process that changed it does
    assert cache.get("cam-1").image_width_px == width + 1  # type: ignore[union-attr]
    uncached = CameraCache(ttl_s=0.0, sessions=sessions, clock=Clock())
    uncached.get("cam-1")
    _resize(sessions, "cam-1", width + 2)
    assert uncached.get("cam-1").image_width_px == width + 2  # type: ignore[union-attr]


def test_a_missing_camera_is_never_remembered(engine: Engine) -> None:
    sessions = make_session_factory(engine)
    cache = CameraCache(ttl_s=60.0, sessions=sessions, clock=Clock())
    assert cache.get("later") is None
    with sessions() as session:
        add_camera(session, "later")  # created by another process
        session.commit()
    assert cache.get("later") is not None
    with sessions() as session, session.begin():
        delete_camera(session, "later")
    # Deleted elsewhere: still remembered until ttl_s, and the frame's insert then fails on its foreign key (404).
    assert cache.get("later") is not None
