#!/bin/sh
# Entrypoint of docker/postgres.Dockerfile: initialise $PGDATA on the first start (its superuser
# POSTGRES_USER with the password POSTGRES_PASSWORD, the database POSTGRES_DB), then run postgres in
# the foreground listening on every address of the container. Runs as the user postgres.
set -eu
user=${POSTGRES_USER:-autotuner}
database=${POSTGRES_DB:-$user}
if [ ! -s "$PGDATA/PG_VERSION" ]; then
    : "${POSTGRES_PASSWORD:?set POSTGRES_PASSWORD: the data directory is empty and its superuser needs a password}"
    pwfile=$(mktemp)
    printf '%s\n' "$POSTGRES_PASSWORD" > "$pwfile"
    # Inside the container (its Unix socket) trust; over TCP, from anywhere, a password.
    initdb --username="$user" --pwfile="$pwfile" --auth-local=trust --auth-host=scram-sha-256 \
        --encoding=UTF8 --locale=C.UTF-8
    rm -f "$pwfile"
    echo "host all all all scram-sha-256" >> "$PGDATA/pg_hba.conf"
    if [ "$database" != postgres ]; then
        # Single-user mode: no server to start and stop for one statement.
        printf 'CREATE DATABASE "%s"\n' "$database" | postgres --single -D "$PGDATA" postgres >/dev/null
    fi
    echo "postgres-entrypoint: initialised $PGDATA (superuser $user, database $database)"
fi
exec postgres -D "$PGDATA" -c listen_addresses='*' "$@"
