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
if [ "$#" -gt 0 ]; then   # the caller chose what to run: one process, as asked
  echo "[test] pytest -m '$marker' $*"
  exec .venv/bin/python -m pytest -m "$marker" -q "$@"
fi
# the pure tests (no sockets, no processes, no wall clock) on two workers; then everything else in one process:
# the flights and the real-time tests measure timing and must not share the machine with each other; the 15
# slowest are listed at the end (where the 30-minute budget goes)
echo "[test] pytest -m '$marker' tests/unit tests/protocol on 2 workers"
status=0
.venv/bin/python -m pytest -m "$marker" -q -n 2 tests/unit tests/protocol || status=$?
[ "$status" = 5 ] && status=0   # 5: nothing selected (the slow set has no pure tests)
echo "[test] pytest -m '$marker' (the rest)"
rest=0
.venv/bin/python -m pytest -m "$marker" -q --durations=15 --ignore=tests/unit --ignore=tests/protocol || rest=$?
[ "$rest" = 5 ] && rest=0
[ "$status" = 0 ] && [ "$rest" = 0 ]
