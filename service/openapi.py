"""The committed OpenAPI document (`openapi/openapi.json`): generated from the app, checked for staleness.

Clients generate code from the committed file, so it must match the code exactly; a test runs `check()` and
fails when a route or schema changed without regenerating. Regenerate with `python -m service.openapi`.
"""

from __future__ import annotations

import argparse
import json
import sys
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


def main(argv: list[str] | None = None) -> int:
    """Write the document (default) or, with --check, exit 1 when the committed one is stale."""
    parser = argparse.ArgumentParser(prog="python -m service.openapi", description=__doc__)
    parser.add_argument("--check", action="store_true", help="Only compare; exit 1 when the file is stale.")
    parser.add_argument("--output", type=Path, default=OPENAPI_PATH, help="Where the document lives.")
    args = parser.parse_args(argv)
    if args.check:
        if is_current(args.output):
            print(f"{args.output} is up to date")
            return 0
        print(f"{args.output} is stale: run python -m service.openapi", file=sys.stderr)
        return 1
    print(f"wrote {write(args.output)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
