"""End-to-end fixtures: the store's throwaway databases (SQLite file, PostgreSQL cluster), re-exported."""

from __future__ import annotations

from tests.store.conftest import migrated_url, postgres_cluster, postgres_template, sqlite_template

__all__ = ["migrated_url", "postgres_cluster", "postgres_template", "sqlite_template"]
