"""Time-boxed soak of the hostile-input property tests (issue 16): each test marked ``fuzz`` runs for at least
``--minutes`` of wall time, in rounds of fresh random examples (one pytest per round, its own hypothesis seed, so
a failure names the seed that reproduces it). Rounds are sized from the first one to last about ``--round-s``.

    .venv/bin/python scripts/fuzz_soak.py --minutes 10 [-k EXPR] [--jobs 2]

Each round runs under a memory cap (``--max-memory-mb``, RLIMIT_AS: unbounded growth ends in MemoryError, a
failure) and a hang watchdog (a round that takes ``--hang-factor`` times its planned length is killed and
reported as a hang). Prints one line per round with its peak memory and a summary per test; exits non-zero on
the first failing round (its output is shown).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FIRST_ROUND_EXAMPLES = 500   # large enough to be randomized (tests/fuzzing.py derandomizes <= 500: use 501)


_COLLECT = """
import sys, pytest
class HypothesisTests:
    @pytest.hookimpl(trylast=True)   # after -m and -k have deselected
    def pytest_collection_modifyitems(self, items):
        for item in items:
            if getattr(getattr(item, "obj", None), "is_hypothesis_test", False):
                print("HYPOTHESIS", item.nodeid)
sys.exit(pytest.main(sys.argv[1:], plugins=[HypothesisTests()]))
"""


def collect(expr: str | None) -> list[str]:
    """The property tests among those marked ``fuzz`` (their plain regression tests need no soak)."""
    cmd = [sys.executable, "-c", _COLLECT, "-m", "fuzz", "--collect-only", "-q", "-p", "no:randomly"]
    if expr:
        cmd += ["-k", expr]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=True).stdout
    return [line.split(" ", 1)[1] for line in out.splitlines() if line.startswith("HYPOTHESIS ")]


def _peak_rss_mb() -> float:
    """Peak resident memory of the largest child so far (ru_maxrss is a maximum over children, in KiB)."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def run_round(test_id: str, examples: int, seed: int, limit_s: float,
              max_memory_mb: int) -> tuple[bool, float, str]:
    """One pytest run of ``examples`` fresh examples; (passed, seconds, output tail). Killed after ``limit_s``."""
    env = dict(os.environ, QUADLINK_FUZZ_EXAMPLES=str(examples))
    cap_bytes = max_memory_mb * 1024 * 1024

    def cap_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (cap_bytes, cap_bytes))

    t0 = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, "-m", "pytest", test_id, "-q", "-p", "no:randomly", "--timeout", "0",
                               f"--hypothesis-seed={seed}"], cwd=REPO, env=env, capture_output=True, text=True,
                              timeout=limit_s, preexec_fn=cap_memory)
    except subprocess.TimeoutExpired as exc:
        tail = (exc.stdout or b"")[-4000:]
        text = tail.decode(errors="replace") if isinstance(tail, bytes) else tail
        return False, time.monotonic() - t0, f"HANG: round killed after {limit_s:.0f} s\n{text}"
    return proc.returncode == 0, time.monotonic() - t0, proc.stdout[-4000:] + proc.stderr[-2000:]


def soak(test_id: str, minutes: float, round_s: float, hang_factor: float,
         max_memory_mb: int) -> tuple[bool, int, float]:
    """Rounds until ``minutes`` have passed; (passed, examples, wall seconds)."""
    t_start = time.monotonic()
    examples, total, seed = FIRST_ROUND_EXAMPLES + 1, 0, 1
    planned_s = 60.0                              # the first round's size is a guess: allow it a generous minute
    while True:
        ok, took_s, output = run_round(test_id, examples, seed, hang_factor * planned_s + 30.0, max_memory_mb)
        total += examples
        elapsed = time.monotonic() - t_start
        print(f"[soak] {test_id}: round {seed}, {examples} examples in {took_s:.0f} s "
              f"({total} in {elapsed / 60:.1f} min, children's peak memory {_peak_rss_mb():.0f} MB)"
              f"{'' if ok else '  FAILED'}", flush=True)
        if not ok:
            print(output, flush=True)
            return False, total, elapsed
        if elapsed >= minutes * 60.0:
            return True, total, elapsed
        rate = examples / max(took_s - 3.0, 0.5 * took_s)   # about 3 s of each round is pytest's start-up
        left_s = minutes * 60.0 - elapsed
        examples = min(4 * examples, max(FIRST_ROUND_EXAMPLES + 1, int(rate * min(round_s, left_s + 5.0))))
        planned_s = examples / rate + 3.0
        seed += 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="wall time per test (default 10)")
    ap.add_argument("--round-s", type=float, default=120.0, help="length of one round (default 120 s)")
    ap.add_argument("-k", dest="expr", default=None, help="pytest -k expression to select tests")
    ap.add_argument("--jobs", type=int, default=1, help="tests soaked at once (default 1)")
    ap.add_argument("--hang-factor", type=float, default=4.0,
                    help="a round taking this many times its planned length is a hang (default 4)")
    ap.add_argument("--max-memory-mb", type=int, default=3000, help="address-space cap of a round (default 3000)")
    a = ap.parse_args()
    tests = collect(a.expr)
    if not tests:
        print("[soak] no fuzz tests selected", file=sys.stderr)
        return 2
    print(f"[soak] {len(tests)} tests, {a.minutes:g} min each, {a.jobs} at once", flush=True)
    try:
        with ThreadPoolExecutor(max_workers=max(1, a.jobs)) as pool:
            results = list(pool.map(lambda t: (t, *soak(t, a.minutes, a.round_s, a.hang_factor,
                                                                     a.max_memory_mb)), tests))
    except KeyboardInterrupt:
        print("[soak] interrupted", file=sys.stderr)
        return 130
    print("[soak] summary")
    for test_id, ok, total, elapsed in results:
        print(f"  {'ok    ' if ok else 'FAILED'} {total:>9} examples  {elapsed / 60:5.1f} min  {test_id}")
    return 0 if all(ok for _, ok, _, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
