"""API keys: every route but `/healthz` and `/readyz` needs `Authorization: Bearer <key>`.

- tokens: how a key looks (`pm_<id>_<secret>`) and is hashed (HMAC-SHA256; why not bcrypt is said there).
- principal: who is calling (admin? limited to which cameras?).
- cache, authenticator: header to Principal, with verified keys cached per process for `api_key_cache_ttl_s`.
- dependencies: `require_key` (put on every router by create_app), `PrincipalDep` and `AdminDep` for routes.
- keys, schemas, cli: issuing keys, their HTTP bodies, and `posemetry keys`.

Nothing is imported here, so `posemetry --help` does not pay for FastAPI and SQLAlchemy.
"""
