"""The FastAPI side of API keys: the app-wide dependency, and the principal for routes that need it.

`create_app` puts `require_key` on every router except health, so a router added later is protected by default.
Routes that need to know who is calling declare `PrincipalDep` (the same dependency: FastAPI runs it once per
request and hands both the same Principal); key management declares `AdminDep`. A route with a `{camera_id}`
path parameter is camera-scoped automatically: a key limited to other cameras gets 403 before the handler runs,
and before the database is asked whether that camera exists, so the answer says nothing about existence. Routes
that take camera ids elsewhere (a query, a body) or list cameras must check `Principal.can_access` themselves.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .authenticator import Authenticator, forbidden
from .middleware import PRINCIPAL_STATE
from .principal import Principal
from .tokens import TOKEN_FORMAT

# Declares the scheme in OpenAPI (and so in /docs' Authorize button); the header is parsed by the Authenticator,
# whose messages say what exactly is wrong.
BEARER = HTTPBearer(
    scheme_name="ApiKey",
    bearerFormat=TOKEN_FORMAT,
    description="An API key: `Authorization: Bearer <key>`. Admin keys come from POSEMETRY_ADMIN_KEY, from "
    "`posemetry serve`'s first start or `posemetry keys create --admin`; admins create the others with POST /v1/keys.",
    auto_error=False,
)


async def require_key(
    request: Request, _declared: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]
) -> Principal:
    """Authenticate the request (401 otherwise) and enforce a scoped key's cameras on `{camera_id}` routes (403)."""
    principal: Principal | None = getattr(request.state, PRINCIPAL_STATE, None)  # from AuthenticateBeforeBody
    if principal is None:
        authenticator: Authenticator = request.app.state.authenticator
        principal = await authenticator.authenticate(request.headers.get("authorization"))
    camera_id = request.path_params.get("camera_id")
    if camera_id is not None and not principal.can_access(camera_id):
        raise forbidden(
            "camera-out-of-scope",
            f"This API key is limited to other cameras than {camera_id!r}; ask an admin for a key that includes it.",
        )
    return principal


async def require_admin(principal: Annotated[Principal, Depends(require_key)]) -> Principal:
    if not principal.admin:
        raise forbidden(
            "admin-key-required",
            "Only admin keys manage API keys and webhooks and read /metrics; this one is not an admin key.",
        )
    return principal


PrincipalDep = Annotated[Principal, Depends(require_key)]
"""The caller of a protected route: whether it is an admin, and which cameras it may use."""
AdminDep = Annotated[Principal, Depends(require_admin)]
"""The caller, who must hold an admin key (403 otherwise)."""


# Documented on every protected operation (create_app adds the problem+json schema).
AUTH_RESPONSE_DESCRIPTIONS: dict[int, str] = {
    401: "No API key, a malformed one, or an unknown, revoked or expired key (problem details, with "
    "`WWW-Authenticate: Bearer`)",
    403: "The key may not do this: a camera outside its scope, or managing keys without an admin key",
}
