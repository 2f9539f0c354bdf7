"""Leases of a plant's loops in PostgreSQL: which daemon of a fleet owns which loop, with an epoch that only grows.

A daemon serves a loop only while it holds the loop's lease. A lease is a
row ``(loop, owner, epoch, expires_at)``; the owner renews it every few
seconds; once it has expired (the owner died, froze or lost the database)
another daemon takes it over and the epoch grows by one. Every time is the
database server's (``now()``): the daemons' clocks never decide who owns
what. A daemon also heartbeats a row of its own ``(name, url, seen_at,
draining)``, so that the daemons alive can split the loops evenly.

Every statement is one atomic statement of PostgreSQL (an UPDATE with its
condition, an INSERT … ON CONFLICT DO UPDATE with its condition): two
daemons racing for one loop can never both get it.
"""

from __future__ import annotations

from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.dialects import postgresql

from autotuner.service.schema import create_tables

_META = sa.MetaData()
_LEASES = sa.Table(
    "leases", _META,
    sa.Column("loop", sa.String(64), primary_key=True),
    sa.Column("owner", sa.String(128)),
    sa.Column("epoch", sa.BigInteger, nullable=False),
    sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
)
_DAEMONS = sa.Table(
    "daemons", _META,
    sa.Column("name", sa.String(128), primary_key=True),
    sa.Column("url", sa.Text, nullable=False),
    sa.Column("seen_at", sa.DateTime(timezone=True), nullable=False),
    sa.Column("draining", sa.Boolean, nullable=False),
)
_NOW = sa.func.now()


@dataclass(frozen=True)
class Member:
    """A daemon of the fleet alive now: its ``name``, the ``url`` its API answers at, whether it is ``draining``."""

    name: str
    url: str
    draining: bool


@dataclass(frozen=True)
class Owner:
    """Who holds a loop's lease: the daemon's ``name`` and ``url`` (None: nobody), the lease's ``epoch``, whether
    it is ``live`` (not expired)."""

    name: str | None
    url: str | None
    epoch: int
    live: bool


class Leases:
    """The leases of the database at ``url`` (SQLAlchemy, PostgreSQL) as seen by daemon ``name`` (API at
    ``api_url``), each held ``ttl`` seconds from its last renewal."""

    def __init__(self, url: str, name: str, api_url: str, ttl: float) -> None:
        self.name, self.api_url, self.ttl = name, api_url, ttl
        self._engine = sa.create_engine(url, pool_size=2, max_overflow=0, pool_pre_ping=True)
        if self._engine.dialect.name != "postgresql":
            raise ValueError(f"leases need PostgreSQL, not {self._engine.dialect.name}")
        with self._engine.begin() as db:
            create_tables(db, _META)

    def close(self) -> None:
        """Let go of the database connections."""
        self._engine.dispose()

    def _later(self) -> sa.ColumnElement[object]:
        return _NOW + sa.text(f"interval '{float(self.ttl)} seconds'")

    def heartbeat(self, draining: bool) -> list[Member]:
        """This daemon is alive (and ``draining`` or not); the daemons alive now (seen within a lease time)."""
        row = {"name": self.name, "url": self.api_url, "seen_at": _NOW, "draining": draining}
        upsert = postgresql.insert(_DAEMONS).values(row)
        upsert = upsert.on_conflict_do_update(index_elements=["name"], set_={
            "url": upsert.excluded.url, "seen_at": _NOW, "draining": upsert.excluded.draining})
        alive = sa.select(_DAEMONS.c.name, _DAEMONS.c.url, _DAEMONS.c.draining).where(
            _DAEMONS.c.seen_at > _NOW - sa.text(f"interval '{float(self.ttl)} seconds'")).order_by(_DAEMONS.c.name)
        with self._engine.begin() as db:
            db.execute(upsert)
            return [Member(r.name, r.url, r.draining) for r in db.execute(alive)]

    def renew(self, held: dict[str, int]) -> dict[str, int]:
        """Renew the leases ``held`` (loop → epoch); the ones still this daemon's (the others were taken over)."""
        if not held:
            return {}
        with self._engine.begin() as db:
            rows = db.execute(sa.update(_LEASES).where(
                sa.tuple_(_LEASES.c.loop, _LEASES.c.epoch).in_(list(held.items())), _LEASES.c.owner == self.name,
            ).values(expires_at=self._later()).returning(_LEASES.c.loop, _LEASES.c.epoch)).all()
        return {r.loop: r.epoch for r in rows}

    def acquire(self, loops: list[str], limit: int) -> dict[str, int]:
        """Take at most ``limit`` of ``loops`` whose lease is free (none yet, expired, or released); loop → its new
        epoch (the old one plus one)."""
        taken: dict[str, int] = {}
        for loop in loops:
            if len(taken) >= limit:
                break
            insert = postgresql.insert(_LEASES).values(loop=loop, owner=self.name, epoch=1,
                                                       expires_at=self._later())
            claim = insert.on_conflict_do_update(
                index_elements=["loop"], set_={"owner": self.name, "epoch": _LEASES.c.epoch + 1,
                                               "expires_at": self._later()},
                where=sa.or_(_LEASES.c.expires_at < _NOW, _LEASES.c.owner.is_(None)))
            with self._engine.begin() as db:
                row = db.execute(claim.returning(_LEASES.c.epoch)).first()
            if row is not None:
                taken[loop] = row.epoch
        return taken

    def release(self, loops: dict[str, int]) -> None:
        """Give up the leases ``loops`` (loop → epoch) at once: another daemon may take them now."""
        for loop, epoch in loops.items():
            with self._engine.begin() as db:
                db.execute(sa.update(_LEASES).where(_LEASES.c.loop == loop, _LEASES.c.owner == self.name,
                                                    _LEASES.c.epoch == epoch).values(owner=None, expires_at=_NOW))

    def owners(self) -> dict[str, Owner]:
        """Every loop's lease: its owner (name and API URL), epoch and whether it is live."""
        query = sa.select(_LEASES.c.loop, _LEASES.c.owner, _DAEMONS.c.url, _LEASES.c.epoch,
                          (_LEASES.c.expires_at > _NOW).label("live")).select_from(
            _LEASES.outerjoin(_DAEMONS, _DAEMONS.c.name == _LEASES.c.owner))
        with self._engine.connect() as db:
            return {r.loop: Owner(r.owner, r.url, r.epoch, bool(r.live) and r.owner is not None)
                    for r in db.execute(query)}
