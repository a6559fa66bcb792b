#!/usr/bin/env bash
# A throwaway PostgreSQL server on loopback for the tuning tests and for trying distributed studies.
#
#   scripts/postgres.sh [start]   install PostgreSQL (apt-get) and psycopg2-binary if missing, start a
#                                 server on 127.0.0.1 on a free port with its data in a temp folder,
#                                 create the database; print the URL (the only line on stdout)
#   scripts/postgres.sh url       print the URL of the running server (exit 1 if none)
#   scripts/postgres.sh stop      stop the server and delete its folder
#
# Idempotent: "start" on a running server only prints its URL. The server never runs as root: when
# started by root it runs as the "postgres" system user (created by the Debian package).
# Settings (environment): SB3_GRAPH_PG_DIR (folder, default /tmp/sb3-graph-postgres-<uid>),
# SB3_GRAPH_PG_DB (database, default sb3graph), SB3_GRAPH_PG_NO_PIP=1 (skip the psycopg2 install),
# PYTHON (the interpreter that needs psycopg2, default python3).
#
# CI:  export SB3_GRAPH_TEST_POSTGRES_URL="$(scripts/postgres.sh)"; trap 'scripts/postgres.sh stop' EXIT
set -euo pipefail

ACTION="${1:-start}"
DIR="${SB3_GRAPH_PG_DIR:-/tmp/sb3-graph-postgres-$(id -u)}"
DB="${SB3_GRAPH_PG_DB:-sb3graph}"
ROLE="sb3graph"
PASSWORD="sb3graph"  # loopback only, throwaway data
PYTHON="${PYTHON:-python3}"
DATA="$DIR/data"

log() { echo "postgres.sh: $*" >&2; }

find_bin() {  # the folder holding pg_ctl and initdb (Debian keeps them off PATH)
    local candidate
    for candidate in $(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V -r); do
        [[ -x "$candidate/pg_ctl" && -x "$candidate/initdb" ]] && { echo "$candidate"; return 0; }
    done
    if command -v pg_ctl >/dev/null && command -v initdb >/dev/null; then
        dirname "$(command -v pg_ctl)"
        return 0
    fi
    return 1
}

as_owner() {  # run a command as the server's (non-root) user
    if [[ "$(id -u)" == 0 ]]; then
        runuser -u postgres -- "$@"
    else
        "$@"
    fi
}

url() { echo "postgresql://$ROLE:$PASSWORD@127.0.0.1:$(cat "$DIR/port")/$DB"; }

running() { [[ -f "$DIR/port" && -d "$DATA" ]] && as_owner "$BIN/pg_ctl" status -D "$DATA" >/dev/null 2>&1; }

install_server() {
    if [[ "$(id -u)" != 0 ]]; then
        log "PostgreSQL is not installed; install it (apt-get install postgresql) or run this script as root"
        exit 1
    fi
    log "installing PostgreSQL with apt-get"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >&2
    apt-get install -y -qq postgresql >&2
}

install_driver() {
    [[ "${SB3_GRAPH_PG_NO_PIP:-0}" == 1 ]] && return 0
    command -v "$PYTHON" >/dev/null || return 0
    if ! "$PYTHON" -c "import psycopg2" 2>/dev/null; then
        log "installing psycopg2-binary into $("$PYTHON" -c 'import sys; print(sys.prefix)')"
        "$PYTHON" -m pip install -q psycopg2-binary >&2
    fi
}

free_port() {
    "$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

BIN="$(find_bin || true)"
case "$ACTION" in
    url)
        [[ -n "$BIN" ]] && running && { url; exit 0; }
        log "no server running in $DIR"
        exit 1
        ;;
    stop)
        if [[ -n "$BIN" ]] && running; then
            as_owner "$BIN/pg_ctl" stop -D "$DATA" -m fast -w >&2
        fi
        rm -rf "$DIR"
        exit 0
        ;;
    start) ;;
    *)
        log "unknown action '$ACTION'; use start, url or stop"
        exit 2
        ;;
esac

if [[ -z "$BIN" ]]; then
    install_server
    BIN="$(find_bin)"
fi
install_driver
if running; then
    url
    exit 0
fi

# A stale folder (server gone, e.g. after a reboot) is started again on a new free port.
mkdir -p "$DIR"
[[ "$(id -u)" == 0 ]] && chown postgres: "$DIR"
if [[ ! -f "$DATA/PG_VERSION" ]]; then
    pwfile="$DIR/pwfile"
    echo "$PASSWORD" > "$pwfile"
    [[ "$(id -u)" == 0 ]] && chown postgres: "$pwfile"
    as_owner "$BIN/initdb" -D "$DATA" -U "$ROLE" --pwfile="$pwfile" --auth-local=trust \
        --auth-host=scram-sha-256 -E UTF8 >"$DIR/initdb.log" 2>&1 || { cat "$DIR/initdb.log" >&2; exit 1; }
    rm -f "$pwfile"
fi
port="$(free_port)"
echo "$port" > "$DIR/port"
as_owner "$BIN/pg_ctl" start -D "$DATA" -w -t 60 -l "$DIR/server.log" \
    -o "-c listen_addresses=127.0.0.1 -p $port -k $DIR -c max_connections=200" >&2 \
    || { cat "$DIR/server.log" >&2; exit 1; }
exists="$(as_owner "$BIN/../bin/psql" -h "$DIR" -p "$port" -U "$ROLE" -d postgres -tAc \
    "SELECT 1 FROM pg_database WHERE datname = '$DB'" 2>/dev/null || true)"
if [[ "$exists" != 1 ]]; then
    as_owner "$BIN/createdb" -h "$DIR" -p "$port" -U "$ROLE" "$DB" >&2
fi
log "server running on 127.0.0.1:$port (data in $DATA; stop with: scripts/postgres.sh stop)"
url
