# PostgreSQL from Debian's `postgresql` package, for docker/compose.fleet.yaml (a fleet's shared history,
# docs/fleet.md). The environment: POSTGRES_PASSWORD (required on the first start), POSTGRES_USER (default
# autotuner: the superuser, whose password that is), POSTGRES_DB (default: POSTGRES_USER). The data directory
# (a volume at /var/lib/postgresql/data) is initialised on the first start (docker/postgres-entrypoint.sh);
# postgres then listens on every address of the container, password (SCRAM) required over TCP.
# Build from the repository root: docker build -f docker/postgres.Dockerfile -t autotuner-postgres .
FROM python:3.11-slim

# postgresql-common first, so that installing postgresql creates no cluster of Debian's own.
RUN apt-get update \
    && apt-get install -y --no-install-recommends postgresql-common \
    && sed -ri 's/^#?\s*create_main_cluster\s*=.*/create_main_cluster = false/' /etc/postgresql-common/createcluster.conf \
    && apt-get install -y --no-install-recommends postgresql \
    && rm -rf /var/lib/apt/lists/* \
    && ln -s "$(ls -d /usr/lib/postgresql/*/bin)" /usr/lib/postgresql/bin \
    && mkdir -p /var/lib/postgresql/data /run/postgresql \
    && chown postgres:postgres /var/lib/postgresql/data /run/postgresql && chmod 700 /var/lib/postgresql/data
ENV PATH=/usr/lib/postgresql/bin:$PATH \
    PGDATA=/var/lib/postgresql/data
COPY docker/postgres-entrypoint.sh /usr/local/bin/postgres-entrypoint
VOLUME /var/lib/postgresql/data
USER postgres
EXPOSE 5432
# SIGINT: postgres's fast shutdown (open sessions are ended); SIGTERM would wait for the daemons to disconnect.
STOPSIGNAL SIGINT
HEALTHCHECK --interval=3s --timeout=3s --start-period=30s --retries=5 \
    CMD pg_isready -q -h 127.0.0.1 -U "${POSTGRES_USER:-autotuner}" -d "${POSTGRES_DB:-${POSTGRES_USER:-autotuner}}"
ENTRYPOINT ["postgres-entrypoint"]
