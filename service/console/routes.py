"""The operator console's page, script and style sheet.

The page is a shell with no data in it, like `/docs`: everything it shows is fetched by its script from the API
with the operator's key (typed once, kept in the tab's sessionStorage, sent as `Authorization: Bearer`), so the
console sees exactly what that key may see and no route here needs a key of its own. The key never travels in a
URL or a cookie; the page sets no cookie at all. A strict Content-Security-Policy allows only this origin's script
and style sheet (no inline script, no eval), images from the API as blobs, and no framing, so an injected string
in a camera id or a webhook URL can show up only as text.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import HTMLResponse, Response

from service import __version__
from service.console.page import STATIC_DIR, render_page
from service.http.dependencies import SettingsDep
from service.http.problems import ProblemError

router = APIRouter(include_in_schema=False)

CONTENT_SECURITY_POLICY = "; ".join(
    (
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self' blob:",
        "connect-src 'self'",
        "base-uri 'none'",
        "form-action 'none'",
        "frame-ancestors 'none'",
    )
)
SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    # The page is tiny and versioned by the package: always fresh, never left in a shared cache.
    "Cache-Control": "no-store",
}
ASSETS = {
    "console.js": "text/javascript; charset=utf-8",
    "console.css": "text/css; charset=utf-8",
    "icon.svg": "image/svg+xml",
}


@router.get("/console", response_class=HTMLResponse)
def console_page(settings: SettingsDep) -> HTMLResponse:
    return HTMLResponse(render_page(__version__, settings.console_refresh_s), headers=SECURITY_HEADERS)


@router.get("/console/{name}")
def console_asset(name: str) -> Response:
    """The page's script, style sheet and icon (no other file of the folder is served)."""
    if name not in ASSETS:
        raise ProblemError(404, "not-found", f"The console has no file {name!r}.")
    return Response((STATIC_DIR / name).read_bytes(), media_type=ASSETS[name], headers=SECURITY_HEADERS)
