"""The committed OpenAPI document (`openapi/openapi.json`): generated from the app, checked for staleness.

Clients generate code from the committed file, so it must match the code exactly; a test runs `check()` and
fails when a route or schema changed without regenerating. Regenerate with `posemetry openapi`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

OPENAPI_PATH = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def openapi_document() -> dict[str, Any]:
    """The app's OpenAPI schema, built against an in-memory database so generating it touches no files."""
    from service.app import create_app
    from service.settings import Settings

    return create_app(Settings(database_url="sqlite://")).openapi()


def render() -> str:
    """Stable text: fixed indentation and a final newline, so regenerating an unchanged API changes nothing."""
    return json.dumps(openapi_document(), indent=2, ensure_ascii=False) + "\n"


def write(path: Path = OPENAPI_PATH) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render(), encoding="utf-8")
    return path


def is_current(path: Path = OPENAPI_PATH) -> bool:
    return path.exists() and path.read_text(encoding="utf-8") == render()
