"""What the tests share: fixtures (registered in tests/conftest.py) and helpers, imported from here by every folder.

- databases, postgres: SQLite files and a throwaway PostgreSQL cluster, migrated once and copied per test.
- app, dispatch: the API in-process with TestClient, a dispatcher that records what it would queue, and the
  helpers that build frames and check problem answers.
- jobs, measure: a real Redis and RQ workers, simulated cameras storing frames; a stored frame measured in place.
- serving: `posemetry serve` as a real process; receiver: a real local webhook receiver.
- logs, scrape: the service's JSON log lines and its Prometheus exposition, parsed.
- geometry: synthetic scenes for the geometry tests, the ideal camera's problem fields, angle errors.
- shared, analyze: where the real models and camera data are, and `posemetry analyze` as a user runs it.
"""
