"""API keys: every route but `/healthz` and `/readyz` needs `Authorization: Bearer <key>`.

The room of the `/v1/keys` routes, and of authenticating every request:

- routes, schemas, service, repository: the key routes, their bodies, issuing keys (also for `posemetry keys`,
  service.cli.keys, and `posemetry serve`'s first admin key), and keys in the store (digests only).
- tokens: how a key looks (`pm_<id>_<secret>`) and is hashed (HMAC-SHA256; why not bcrypt is said there).
- principal: who is calling (admin? limited to which cameras?).
- cache, authenticator: header to Principal, with verified keys cached per process for `api_key_cache_ttl_s`.
- middleware, dependencies: the check before a body is read, `require_key` (put on every router by create_app),
  `PrincipalDep` and `AdminDep` for routes.

Nothing is imported here, so `posemetry --help` does not pay for FastAPI and SQLAlchemy.
"""
