"""Run every benchmark (``benchmarks/bench_*.py``) one after the other and print their figures.

    python benchmarks/run_all.py            # all
    python benchmarks/run_all.py sitl vo    # those whose file name contains one of the words

Benchmarks are kept apart from the tests: they measure speed and quality figures against the
targets and reference implementations they name; the tests assert behaviour.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    selected = [p for p in sorted(HERE.glob("bench_*.py")) if not argv or any(w in p.stem for w in argv)]
    if not selected:
        print("no benchmark matches", argv, file=sys.stderr)
        return 2
    failed = []
    for path in selected:
        print(f"\n=== {path.name} ===", flush=True)
        start = time.monotonic()
        code = subprocess.call([sys.executable, str(path)], cwd=HERE.parent)
        print(f"--- {path.name}: exit {code} in {time.monotonic() - start:.1f} s", flush=True)
        if code:
            failed.append(path.name)
    if failed:
        print("failed:", ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
