"""gearbench db upgrade URL: create or upgrade the central results database."""
from __future__ import annotations

NAME = "db"
HELP = "Central results database (PostgreSQL): 'upgrade URL' applies the schema migrations, 'status URL' shows the version."


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="db_action", metavar="ACTION", required=True)
    for action, text in (("upgrade", "apply the schema migrations not yet applied"),
                         ("status", "print the schema version and the run count per station")):
        s = sub.add_parser(action, help=text, description=text)
        s.add_argument("url", metavar="URL", help="postgresql://USER@HOST[:PORT]/DB")


def run(args) -> int:
    from ..fleet import migrations
    from ..station.config import central_url, target_name
    from ..fleet.push import connect

    url = central_url(args.url)
    name = target_name(url)
    with connect(url) as conn:
        if args.db_action == "upgrade":
            applied = migrations.upgrade(conn)
            for version, what in applied:
                print(f"applied migration {version}: {what}")
            print(f"{name}: schema version {migrations.current_version(conn)} "
                  f"({'up to date' if not applied else f'{len(applied)} applied'})")
            return 0
        version = migrations.current_version(conn)
        print(f"{name}: schema version {version} (this gearbench: {migrations.LATEST})")
        if version:
            for station, n, last in conn.execute(
                    "SELECT s.station_id, count(r.run_id), max(r.started_utc) FROM stations s "
                    "LEFT JOIN runs r USING (station_id) GROUP BY s.station_id ORDER BY s.station_id"):
                print(f"  {station:<24}{n:>8} runs  last {last}")
    return 0 if version == migrations.LATEST else 1
