"""Query strings are as strict as bodies: an unknown parameter, or a single-valued one given twice, is a 422.

FastAPI ignores query parameters a route does not declare and keeps the last of repeated ones, so
`GET .../violations?sinse=2026-01-01T00:00:00Z` would silently answer for the default window, and
`?limit=10&limit=1000` would depend on which value a proxy kept. Request bodies already refuse unknown fields for
the same reason; this dependency, on every router, does the same for the query string and reports it in the same
problem format (`loc: ["query", name]`).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Iterator

from fastapi import Request
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from starlette.routing import BaseRoute

_SEQUENCES = (list, tuple, set, frozenset)


def _takes_several(annotation: object) -> bool:
    origin = typing.get_origin(annotation)
    if origin in _SEQUENCES:
        return True
    return origin in (typing.Union, types.UnionType) and any(_takes_several(a) for a in typing.get_args(annotation))


def _query_fields(dependant: Dependant) -> Iterator[tuple[str, bool]]:
    """(name, takes several values) of every query parameter of a route and of its dependencies."""
    for field in dependant.query_params:
        yield field.alias, _takes_several(field.field_info.annotation)
    for sub in dependant.dependencies:
        yield from _query_fields(sub)


def _declared(route: BaseRoute) -> dict[str, bool]:
    """Read per request (routes are not hashable), and only for requests with a query string: microseconds."""
    dependant = getattr(route, "dependant", None)
    return {} if dependant is None else dict(_query_fields(dependant))


async def known_query_only(request: Request) -> None:
    """Refuse undeclared query parameters and repeated single-valued ones (router dependency)."""
    route = request.scope.get("route")
    if route is None or not request.query_params:
        return
    declared = _declared(route)
    errors = []
    for name in request.query_params.keys():  # a multi-dict: keys() gives each name once
        values = request.query_params.getlist(name)
        if name not in declared:
            errors.append(
                {"loc": ("query", name), "msg": "Unknown query parameter", "type": "extra_forbidden", "input": values}
            )
        elif len(values) > 1 and not declared[name]:
            errors.append(
                {
                    "loc": ("query", name),
                    "msg": f"Given {len(values)} times; give it once",
                    "type": "duplicate_parameter",
                    "input": values,
                }
            )
    if errors:
        raise RequestValidationError(errors)
