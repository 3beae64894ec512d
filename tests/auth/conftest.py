"""The store's database fixtures (SQLite, and a throwaway PostgreSQL cluster), re-exported for pytest."""

from __future__ import annotations

from tests.store import conftest as store_fixtures

backend = store_fixtures.backend
database_url = store_fixtures.database_url
migrated_url = store_fixtures.migrated_url
postgres_cluster = store_fixtures.postgres_cluster
postgres_template = store_fixtures.postgres_template
sqlite_template = store_fixtures.sqlite_template
