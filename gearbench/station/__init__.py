"""The run on one tester: plan → sequence → records → outputs.

- ``plan``: the profile's steps as a plain list of typed actions
  (``Segment | Prompt | Analyse``), pure functions, no I/O.
- ``sequencer``: plays a plan on the drives, segment by segment, and publishes
  every sample and result as records; ``adaptive`` ends a step once its quantity
  is known.
- ``records``: the record stream (run start, samples, results, run stop) and its
  subscribers; ``recorder`` (Arrow/Parquet traces), ``results`` (result.json,
  junit.xml), ``database`` (the station SQLite), ``console`` (the operator's
  progress) consume it.
- ``analyse``: recorded steps → the pure analysis (column re-arranging only).
- ``config``: the station's name, central database URL and trace store.

The station talks to drives through ``gearbench.drives``; it never imports the
simulation (``gearbench.sim``) or the emulated drives (``gearbench.emulate``).
"""
