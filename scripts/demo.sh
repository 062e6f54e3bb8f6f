#!/usr/bin/env bash
# Set up (scripts/setup.sh), then fly the paper's experiment in the SITL and write a flight report.
#   scripts/demo.sh [quadlink demo options, e.g. --duration 60 --out flight-report]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/quadlink demo "$@"
