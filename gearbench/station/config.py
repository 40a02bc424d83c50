"""Where a station finds its name and its central database.

Precedence, first found wins:

- central URL: ``--central URL``, ``$GEARBENCH_CENTRAL``, ``central:`` in the station config;
- station name: ``$GEARBENCH_STATION``, ``station:`` in the station config, the host name.

The station config is ``$GEARBENCH_STATION_CONFIG``, else ``station.yaml`` beside the
station database (e.g. ``results/station.yaml``)::

    station: line3-eol-2
    central: postgresql://gearbench@db.plant.local/gearbench
    trace_store: s3://plant-traces/line3      # where run folders are archived (optional)
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

from ..errors import GearbenchError


def station_config(db_path: str | Path | None = None) -> dict:
    env = os.environ.get("GEARBENCH_STATION_CONFIG")
    p = Path(env) if env else (Path(db_path).parent / "station.yaml" if db_path else None)
    if p is None or not p.exists():
        if env:
            raise GearbenchError(f"{p}: station config named by GEARBENCH_STATION_CONFIG not found; "
                                 f"fix the variable or create the file")
        return {}
    import yaml

    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}" if mark else ""
        raise GearbenchError(f"{p}{where}: not valid YAML ({getattr(exc, 'problem', exc)}); "
                             f"fix the station config") from None
    if not isinstance(data, dict):
        raise GearbenchError(f"{p}: a station config is a mapping (station:, central:, trace_store:)")
    unknown = set(data) - {"station", "central", "trace_store"}
    if unknown:
        raise GearbenchError(f"{p}: unknown key(s) {', '.join(sorted(unknown))}; "
                             f"allowed: station, central, trace_store")
    return data


def default_station(db_path: str | Path | None = None) -> str:
    return (os.environ.get("GEARBENCH_STATION") or str(station_config(db_path).get("station") or "")
            or socket.gethostname())


def central_url(arg: str | None, db_path: str | Path | None = None) -> str | None:
    url = arg or os.environ.get("GEARBENCH_CENTRAL") or station_config(db_path).get("central")
    if url and not str(url).startswith(("postgresql://", "postgres://")):
        raise GearbenchError(f"central database '{url}': expected a postgresql://USER@HOST[:PORT]/DB URL")
    return url or None


def trace_store(db_path: str | Path | None = None) -> str | None:
    return os.environ.get("GEARBENCH_TRACE_STORE") or station_config(db_path).get("trace_store")


def target_name(url: str) -> str:
    """The central database as a name without credentials (``host:port/db``), the key
    under which the outbox remembers what landed there."""
    from psycopg.conninfo import conninfo_to_dict

    try:
        d = conninfo_to_dict(url)
    except Exception as exc:
        raise GearbenchError(f"central database URL: {exc}; expected postgresql://USER@HOST[:PORT]/DB") from None
    return f"{d.get('host', 'localhost')}:{d.get('port', 5432)}/{d.get('dbname', '')}"
