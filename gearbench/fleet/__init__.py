"""A plant's central results database (PostgreSQL) fed from the stations' outboxes.

- ``migrations``: the versioned schema, applied by ``gearbench db upgrade URL``.
- ``push``: the station SQLite is the outbox; ``push_pending`` moves its finished
  runs to PostgreSQL, idempotently (``CentralPush`` does it after each run,
  ``gearbench sync`` after an outage).
- ``query``: one query API over a station SQLite or the central database.
- ``config``: where the central URL and the station's name come from.
- ``pgtemp``: a throwaway PostgreSQL cluster for tests and benchmarks.
"""
