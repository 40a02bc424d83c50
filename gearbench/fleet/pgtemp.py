"""A throwaway PostgreSQL cluster (tests, benchmarks): initdb in a temporary folder,
started with pg_ctl on a free loopback port, removed on stop.

    with TempPostgres() as pg:          # PostgreSQLUnavailable if no server is installed
        url = pg.url                    # postgresql://postgres@127.0.0.1:PORT/postgres
        pg.stop(); pg.start()           # an outage, for the outbox tests

Runs the server as the ``postgres`` user when started as root (PostgreSQL refuses root).
"""
from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


class PostgreSQLUnavailable(RuntimeError):
    pass


def find_bindir() -> Path | None:
    env = os.environ.get("GEARBENCH_PG_BINDIR")
    cands = ([env] if env else []) + sorted(glob.glob("/usr/lib/postgresql/*/bin"), reverse=True)
    which = shutil.which("pg_ctl")
    if which:
        cands.append(str(Path(which).parent))
    for c in cands:
        if c and (Path(c) / "initdb").exists() and (Path(c) / "pg_ctl").exists():
            return Path(c)
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TempPostgres:
    def __init__(self, *, max_connections: int = 100):
        self.bindir = find_bindir()
        if self.bindir is None:
            raise PostgreSQLUnavailable("PostgreSQL server binaries (initdb, pg_ctl) not found; "
                                        "apt-get install postgresql")
        self.max_connections = max_connections
        self.tmp = Path(tempfile.mkdtemp(prefix="gearbench-pg-"))
        self.data = self.tmp / "data"
        self.port = free_port()
        self.as_postgres = os.geteuid() == 0
        self.url = f"postgresql://postgres@127.0.0.1:{self.port}/postgres"
        self._initdb()

    def _cmd(self, *args: str) -> list[str]:
        if self.as_postgres:
            return ["runuser", "-u", "postgres", "--", *args]
        return list(args)

    def _run(self, *args: str, timeout: float = 120) -> None:
        p = subprocess.run(self._cmd(*args), capture_output=True, text=True, timeout=timeout)
        if p.returncode != 0:
            raise PostgreSQLUnavailable(f"{Path(args[0]).name} failed: {(p.stderr or p.stdout).strip()[-400:]}")

    def _initdb(self) -> None:
        if self.as_postgres:
            shutil.chown(self.tmp, "postgres")
        self._run(str(self.bindir / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust",
                  "-E", "UTF8", "--no-sync")

    def start(self) -> "TempPostgres":
        opts = (f"-c listen_addresses=127.0.0.1 -p {self.port} -c unix_socket_directories={self.tmp} "
                f"-c fsync=off -c synchronous_commit=off -c full_page_writes=off "
                f"-c max_connections={self.max_connections} -c shared_buffers=64MB")
        self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-o", opts, "-l",
                  str(self.tmp / "log"), "-w", "-t", "60", "start")
        return self

    def stop(self, mode: str = "fast") -> None:
        if (self.data / "postmaster.pid").exists():
            self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "stop")

    def wait_ready(self, timeout_s: float = 30) -> None:
        import psycopg

        t_end = time.monotonic() + timeout_s
        while True:
            try:
                psycopg.connect(self.url, connect_timeout=2).close()
                return
            except psycopg.OperationalError:
                if time.monotonic() > t_end:
                    raise
                time.sleep(0.2)

    def cleanup(self) -> None:
        try:
            self.stop("immediate")
        finally:
            shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "TempPostgres":
        try:
            self.start()
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.cleanup()
