#!/usr/bin/env bash
# Install what the test suite needs, only what is missing, and run it: README's test command, and .ci/run's.
#
#   tests/setup-and-run.sh [PYTEST ARGUMENTS...]      (none: -n 2 -q, the whole suite)
#
# 1. The system programs some tests use, from apt (as root, or through sudo): Chromium (the browser tests;
#    not needed with $AUTOTUNER_CHROMIUM), PostgreSQL (the history tests; not needed with $AUTOTUNER_PG_BIN) and
#    Node.js with npm (the node-opcua test). Node.js first and npm only if it is still missing then: Debian's
#    nodejs comes without npm (its own package), while NodeSource's nodejs carries npm and Debian's npm
#    conflicts with it ("held broken packages"), so asking apt for both at once fails on such a machine.
#    If an install fails, the package lists are refreshed (apt-get update) and it is tried once more.
# 2. node-opcua-client at its locked version into tests/opcua_node/node_modules (npm ci).
# 3. A virtual environment ($VENV, default .venv, created if absent) with the project and its test extras.
# 4. pytest in it, from the repository's root; the script's exit code is pytest's.
#
# Environment: PYTHON (default python3) makes the venv; VENV; DRY_RUN=1 prints the commands that install or
# run something instead of running them (the checks of what is missing still look at this machine).
set -euo pipefail

cd "${BASH_SOURCE[0]%/*}/.."
PYTHON="${PYTHON:-python3}"
VENV="${VENV:-.venv}"

run() {
    if [[ "${DRY_RUN:-}" == 1 ]]; then
        echo "+ $*"
    else
        "$@"
    fi
}

apt_install() {
    local as_root=()
    if (( EUID != 0 )); then
        command -v sudo >/dev/null || {
            echo "error: $* missing: install them as root (apt-get install $*), or run this script as root" >&2
            exit 2
        }
        as_root=(sudo)
    fi
    export DEBIAN_FRONTEND=noninteractive
    run "${as_root[@]}" apt-get install -y -q "$@" ||
        { run "${as_root[@]}" apt-get update -q && run "${as_root[@]}" apt-get install -y -q "$@"; }
}

missing=()
[[ -n "${AUTOTUNER_CHROMIUM:-}" ]] || command -v chromium >/dev/null || missing+=(chromium)
[[ -n "${AUTOTUNER_PG_BIN:-}" ]] || compgen -G "/usr/lib/postgresql/*/bin/pg_ctl" >/dev/null ||
    missing+=(postgresql)
command -v node >/dev/null || missing+=(nodejs)
if (( ${#missing[@]} )); then
    apt_install "${missing[@]}"
fi
if ! command -v npm >/dev/null; then
    apt_install npm || {
        echo "error: node is installed but npm is not, and apt could not install Debian's npm beside this" \
             "nodejs (a NodeSource nodejs carries its own npm: reinstall that nodejs)" >&2
        exit 2
    }
fi

run npm ci --prefix tests/opcua_node --no-audit --no-fund --loglevel=error

[[ -x "$VENV/bin/python" ]] || run "$PYTHON" -m venv "$VENV"
run "$VENV/bin/pip" install --quiet -e ".[test]"

(( $# )) || set -- -n 2 -q
run "$VENV/bin/python" -m pytest "$@"
