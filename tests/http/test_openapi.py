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


def _refs(node: object) -> set[str]:
    if isinstance(node, dict):
        found = {node["$ref"]} if isinstance(node.get("$ref"), str) else set()
        return found.union(*(_refs(value) for value in node.values()))
    if isinstance(node, list):
        return set().union(*(_refs(value) for value in node))
    return set()


def test_every_reference_resolves() -> None:
    """Bodies read by service.http.json_body are declared by hand; their schemas must still be in the document."""
    document = openapi_document()
    schemas = document["components"]["schemas"]
    refs = _refs(document)
    assert "#/components/schemas/KeypointFrame" in refs
    for ref in refs:
        assert ref.startswith("#/components/schemas/") and ref.rsplit("/", 1)[1] in schemas, ref
    body = document["paths"]["/v1/cameras/{camera_id}/keypoints"]["post"]["requestBody"]
    assert body["required"] is True
    assert set(schemas["KeypointFrame"]["required"]) == {"timestamp", "people"}
