"""JSON request bodies parsed and validated in one pass by pydantic-core, for the hot ingest routes.

FastAPI decodes a body with the standard library's `json.loads` and then validates the Python objects; for a
frame of 20 COCO-17 people (about 1 000 numbers) those two steps were a quarter of the API's CPU per frame.
`model_validate_json` parses straight into the model in Rust. Errors are re-raised as FastAPI's
RequestValidationError with the `body` prefix FastAPI would have given them, so clients see the same
problem documents (400 for malformed JSON, 422 naming each bad field) either way.

A route that reads its body this way declares no body parameter, so its OpenAPI request body is declared with
`openapi_body(Model)`, and the app registers the model's schema with `register_body_schemas`.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterable
from typing import Any, TypeVar

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError

ModelT = TypeVar("ModelT", bound=BaseModel)
_REF_TEMPLATE = "#/components/schemas/{model}"


def json_body(model: type[ModelT]) -> Callable[[Request], Awaitable[ModelT]]:
    """A dependency yielding the request body as `model` (async: no thread hop)."""

    async def parse(request: Request) -> ModelT:
        raw = await request.body()
        try:
            return model.model_validate_json(raw)
        except ValidationError as exc:
            errors = [{**error, "loc": ("body", *error["loc"])} for error in exc.errors(include_url=False)]
            raise RequestValidationError(errors) from None

    return parse


def openapi_body(model: type[BaseModel], description: str | None = None) -> dict[str, Any]:
    """`openapi_extra` for a route whose body is `model`, read by `json_body` rather than declared."""
    body: dict[str, Any] = {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": _REF_TEMPLATE.format(model=model.__name__)}}},
    }
    if description:
        body["description"] = description
    return {"requestBody": body}


def register_body_schemas(app: FastAPI, models: Iterable[type[BaseModel]]) -> None:
    """Add the schemas of bodies declared with `openapi_body` to the app's OpenAPI components.

    FastAPI lists only the models it sees in signatures; the `$ref` that `openapi_body` puts on a route would
    otherwise point nowhere.
    """
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = generate()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in models:
            definition = model.model_json_schema(ref_template=_REF_TEMPLATE)
            for name, sub in definition.pop("$defs", {}).items():
                components.setdefault(name, sub)
            components.setdefault(model.__name__, definition)
        schema["components"]["schemas"] = dict(sorted(components.items()))
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
