"""The history database's tables, created once even when a fleet's daemons start together."""

from __future__ import annotations

import sqlalchemy as sa

# The PostgreSQL advisory lock key under which tables are created (any constant shared by every daemon).
SCHEMA_LOCK = 0x61757475


def create_tables(db: sa.Connection, meta: sa.MetaData) -> None:
    """Create ``meta``'s missing tables in ``db``, within its transaction. On PostgreSQL under an advisory lock
    held until the transaction ends: two servers' CREATE TABLE at once both find the table missing, and one
    then fails on the catalog's unique index (three daemons of a fleet started together: one exited)."""
    if db.dialect.name == "postgresql":
        db.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"), {"key": SCHEMA_LOCK})
    meta.create_all(db)
