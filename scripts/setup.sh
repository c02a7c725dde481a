#!/usr/bin/env bash
# One-time set-up of a fresh machine for teachpath; safe to re-run (it only does what is missing).
#   1. Debian's libusb-1.0-0, which the Open3D wheel links against, installed with apt-get if absent;
#   2. a virtual environment in .venv with the project installed editable, with its dev extra;
#   3. the pendant's browser libraries (three.js, Swagger UI, ReDoc; package-lock.json) with
#      `npm ci --ignore-scripts`, copied into service/ui/vendor/ (scripts/vendor-ui.sh);
#   4. Debian's curl and jq, for the service guide's REST walk-through (a test runs it);
#   5. Debian's chromium, which the pendant's browser tests (tests/ui, Playwright) drive;
#   6. Debian's postgresql, whose server the database tests start in a temporary folder;
#   7. the compiled kernels (recon/_kernels.c, by setup.py; gcc and Python's headers from Debian
#      if missing), compiled again whenever their source or setup.py changed (.venv/.kernels).
# The stamp file .venv/.installed records the pyproject.toml and constraints.txt (the exact versions)
# it was installed from, so a changed dependency list triggers a re-install and an unchanged one
# costs nothing.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
VENV=.venv
STAMP=$VENV/.installed

have_libusb() { ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; }

apt_install() {
    SUDO=""
    if [ "$(id -u)" != 0 ]; then
        if command -v sudo >/dev/null; then SUDO=sudo; else
            echo "setup: $* is missing and this user is not root; run 'apt-get install $*' as root" >&2
            exit 1
        fi
    fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@" >/dev/null
}

if [ "${1:-}" = "--bench-tools" ]; then
    # The API latency benchmark drives the server with wrk (a C load generator); the speed
    # benchmark reads each command's peak memory from GNU time.
    command -v wrk >/dev/null || { echo "setup: installing wrk"; apt_install wrk; }
    [ -x /usr/bin/time ] || { echo "setup: installing time (GNU time)"; apt_install time; }
    exit 0
fi

if ! have_libusb; then
    echo "setup: installing Debian package libusb-1.0-0 (needed by Open3D)"
    apt_install libusb-1.0-0
    have_libusb || { echo "setup: libusb-1.0-0 still not found after apt-get" >&2; exit 1; }
fi

# The pendant's libraries: again only when package-lock.json changed since the last copy.
lock=$(sha256sum package-lock.json | cut -d' ' -f1)
if [ "$(cat service/ui/vendor/.lock-sha256 2>/dev/null)" != "$lock" ]; then
    if ! command -v npm >/dev/null; then
        echo "setup: installing Debian packages nodejs and npm (for the pendant's libraries)"
        apt_install nodejs npm
    fi
    echo "setup: installing the pendant's browser libraries (npm ci) into service/ui/vendor"
    npm ci --ignore-scripts --omit=peer --no-audit --no-fund --loglevel=error >/dev/null
    scripts/vendor-ui.sh node_modules service/ui/vendor
fi

# curl and jq: the service guide's REST walk-through uses them, and a test runs it.
missing=""
for tool in curl jq; do command -v "$tool" >/dev/null || missing="$missing $tool"; done
if [ -n "$missing" ]; then
    echo "setup: installing Debian package(s)$missing (for the service guide's REST walk-through)"
    # shellcheck disable=SC2086 - one word per package
    apt_install $missing
fi

# PostgreSQL's server: the store and API suites also run against a real one, which the tests
# start in a temporary folder (tests/postgres.py); Debian's package, never a download.
if ! ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1; then
    echo "setup: installing Debian package postgresql (for the database tests)"
    apt_install --no-install-recommends postgresql
fi

# The browser the UI tests drive (Playwright, never its own downloaded browsers).
if ! command -v chromium >/dev/null; then
    echo "setup: installing Debian package chromium (for the pendant's browser tests)"
    apt_install --no-install-recommends chromium fonts-liberation
fi

# pip warns about every package-index folder this machine lists but lacks; show its output only
# when it fails, without those lines.
quiet_pip() {
    local log
    log=$(mktemp)
    if ! "$VENV/bin/python" -m pip "$@" >"$log" 2>&1; then
        grep -v -e 'is ignored: it is neither' "$log" >&2
        rm -f "$log"
        return 1
    fi
    rm -f "$log"
}

# The compiled kernels (recon/_kernels.c, setup.py) need a C compiler and Python's headers.
if ! command -v cc >/dev/null && ! command -v gcc >/dev/null; then
    echo "setup: installing Debian package gcc (to compile teachpath's kernels)"
    apt_install gcc libc6-dev
fi
has_python_headers() {
    "$PYTHON" -c 'import os, sys, sysconfig; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'
}
if ! has_python_headers; then
    echo "setup: installing Debian package python3-dev (Python's headers, for the kernels)"
    apt_install python3-dev
fi

# The kernels again whenever their source or build flags changed since they were built (an
# editable install does not rebuild them by itself): the stamp holds the checksum they were
# built from.
KERNEL_STAMP=$VENV/.kernels
kernels_want=$(cat recon/_kernels.c setup.py | sha256sum | cut -d' ' -f1)
rebuild_kernels() {
    echo "setup: compiling teachpath's kernels (recon/_kernels.c)"
    rm -f recon/_kernels*.so
    quiet_pip install -q --no-deps -e .
    "$VENV/bin/python" -c 'import recon._kernels' || {
        echo "setup: the kernels did not build (see above)" >&2
        exit 1
    }
    echo "$kernels_want" > "$KERNEL_STAMP"
}

want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    if [ "$(cat "$KERNEL_STAMP" 2>/dev/null)" != "$kernels_want" ] \
        || ! ls recon/_kernels*.so >/dev/null 2>&1; then
        rebuild_kernels
    fi
    exit 0
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
echo "setup: installing teachpath and its dependencies into $VENV"
quiet_pip install -q --upgrade pip
quiet_pip install -q -c constraints.txt -e '.[all,dev]'
"$VENV/bin/python" -c 'import recon._kernels' || {
    echo "setup: the kernels did not build (see above)" >&2
    exit 1
}
echo "$kernels_want" > "$KERNEL_STAMP"
echo "$want" > "$STAMP"
