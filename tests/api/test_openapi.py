"""The committed openapi/openapi.json must be what the code generates."""

from __future__ import annotations

from service.openapi import OPENAPI_PATH, is_current, openapi_document


def test_committed_openapi_is_current() -> None:
    assert is_current(), f"{OPENAPI_PATH} is stale: regenerate it with `posemetry openapi`"


def test_contract_paths_are_present() -> None:
    paths = openapi_document()["paths"]
    expected = {
        "/v1/cameras": {"get"},
        "/v1/cameras/{camera_id}": {"put", "get", "delete"},
        "/v1/cameras/{camera_id}/keypoints": {"post"},
        "/v1/cameras/{camera_id}/calibration": {"get", "post", "delete"},
        "/v1/cameras/{camera_id}/calibration/history": {"get"},
        "/v1/cameras/{camera_id}/frames/{frame_id}": {"get"},
        "/v1/cameras/{camera_id}/distances": {"post"},
        "/v1/cameras/{camera_id}/violations": {"get"},
        "/healthz": {"get"},
        "/readyz": {"get"},
    }
    for path, methods in expected.items():
        assert methods <= set(paths[path]), path
