"""What people see of a run: the per-unit report (``unit_report``, HTML/PDF), its
``plots``, and the live view in Rerun (``live``). Reads the station's records and
files; never drives anything."""
