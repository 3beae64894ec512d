"""The fixtures every test folder may use, from tests/support (helpers are imported from there, never from a
conftest): databases (SQLite files and a throwaway PostgreSQL), the API in-process, a real Redis with RQ workers,
and the service's JSON log lines."""

pytest_plugins = ["tests.support.databases", "tests.support.app", "tests.support.jobs", "tests.support.logs"]
