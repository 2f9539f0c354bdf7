"""A PostgreSQL server of its own for a benchmark or a test: the distribution's programs, a temporary directory, a
free localhost port (Debian: ``apt-get install postgresql``; ``AUTOTUNER_PG_BIN`` names another directory of
``initdb`` and ``pg_ctl``). As root, the server runs as user ``postgres``."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path


def postgres_bin() -> Path:
    """The directory of the PostgreSQL server programs; FileNotFoundError saying what to install."""
    if os.environ.get("AUTOTUNER_PG_BIN"):
        return Path(os.environ["AUTOTUNER_PG_BIN"])
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parts[-3]))
    if not found:
        raise FileNotFoundError("no PostgreSQL server: apt-get install postgresql (Debian), or set AUTOTUNER_PG_BIN "
                                "to the directory of initdb and pg_ctl")
    return found[-1].parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def temporary_postgres() -> Iterator[str]:
    """Run a PostgreSQL server until the block ends; the SQLAlchemy URL of its maintenance database."""
    bin_dir = postgres_bin()
    as_server = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
    home = Path(tempfile.mkdtemp(prefix="autotuner-pg-"))
    if as_server:
        shutil.chown(home, "postgres")
    data, port = home / "data", _free_port()
    subprocess.run([*as_server, str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres",
                    "-E", "UTF8", "--no-sync"], check=True, capture_output=True)
    options = f"-p {port} -k {home} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=300"
    try:  # (a start that fails half way may have left a server running: stopped below)
        subprocess.run([*as_server, str(bin_dir / "pg_ctl"), "-D", str(data), "-o", options, "-l",
                        str(home / "log"), "-w", "-t", "60", "start"], check=True, capture_output=True)
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*as_server, str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "stop"],
                       capture_output=True)
        shutil.rmtree(home, ignore_errors=True)


def new_database(server: str) -> str:
    """A new, empty database on the server whose maintenance database is ``server`` (a URL); its URL."""
    import sqlalchemy as sa

    name = f"autotuner_{uuid.uuid4().hex[:12]}"
    engine = sa.create_engine(server, isolation_level="AUTOCOMMIT")
    with engine.connect() as db:
        db.execute(sa.text(f"CREATE DATABASE {name}"))
    engine.dispose()
    return server.rsplit("/", 1)[0] + "/" + name
