#!/usr/bin/env bash
# Set up (scripts/setup.sh --test), then lint and run the test suite.
#   scripts/test.sh            the suite without the long SITL flights (what CI runs)
#   scripts/test.sh --slow     only the long flights (the full-length demo flight and soak runs)
#   scripts/test.sh -- ARGS    extra pytest arguments
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
marker="not slow"
if [ "${1:-}" = "--slow" ]; then marker="slow"; shift; fi
[ "${1:-}" = "--" ] && shift
echo "[test] ruff"
.venv/bin/ruff check .
echo "[test] mypy"
.venv/bin/mypy quadlink harness firmware_bridge perception companion teleop sim_sitl
echo "[test] mkdocs build --strict"
.venv/bin/mkdocs build --strict --quiet --site-dir "$(mktemp -d)"
echo "[test] pytest -m '$marker'"
exec .venv/bin/python -m pytest -m "$marker" -q "$@"
