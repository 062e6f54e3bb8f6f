#!/usr/bin/env bash
# Set up quadlink on a fresh Debian/Ubuntu machine: system packages, a virtualenv in .venv, the package.
#   scripts/setup.sh          runtime (what the demo needs)
#   scripts/setup.sh --test   plus the test tools (pytest, hypothesis, MAVSDK, headless Chromium)
# Idempotent: a second run only checks. Needs root (or sudo) for the Debian packages.
set -euo pipefail
cd "$(dirname "$0")/.."
want_test=0
[ "${1:-}" = "--test" ] && want_test=1

say() { echo "[setup] $*"; }

# --- Debian packages -------------------------------------------------------------------------
# open3d links libusb-1.0 and libgomp; OpenGL/EGL stubs for pybullet's and open3d's imports;
# python3-venv for the virtualenv; chromium for the operator-view screenshot test;
# the board firmware (firmware/, C for the ATmega1284P) and the SITL's simavr board (--board avr): avr-gcc,
# avr-libc, simavr and its headers, libelf, make and the host compiler for the shim and the host unit tests.
debs=(libusb-1.0-0 libgomp1 libgl1 libegl1 gcc make gcc-avr avr-libc binutils-avr simavr libsimavr-dev libelf-dev)
python3 -c "import ensurepip, venv" 2>/dev/null || debs+=(python3-venv python3-pip)
[ "$want_test" = 1 ] && debs+=(chromium)
missing=()
for pkg in "${debs[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    say "installing Debian packages: ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    say "warning: no apt-get; install these yourself: ${missing[*]}"
  fi
fi

# --- Python ----------------------------------------------------------------------------------
PY=${PYTHON:-python3}
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "[setup] Python >= 3.11 required" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  say "creating virtualenv .venv"
  "$PY" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
fi
extras=""
[ "$want_test" = 1 ] && extras="[dev]"
stamp=".venv/.quadlink-installed${extras}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  say "installing quadlink${extras} and its dependencies into .venv (a minute or two the first time)"
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".${extras}"
  touch "$stamp"
fi
.venv/bin/python -c "import open3d, pybullet, cv2, pymavlink" 2>/dev/null >/dev/null \
  || { echo "[setup] the installed packages do not import; see the error above" >&2; exit 1; }
# --- the board firmware and the SITL's simavr shim -------------------------------------------
say "building the FlightCtrl firmware (make -C firmware) and the simavr shim"
make -s -C firmware >/dev/null || { echo "[setup] the firmware did not build; see: make -C firmware" >&2; exit 1; }
.venv/bin/python -m sim_sitl.avr.build >/dev/null || { echo "[setup] the simavr shim did not build" >&2; exit 1; }
say "ready: $(.venv/bin/quadlink --version)"
