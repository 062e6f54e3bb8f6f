"""Build the simavr shim (``shim.c``) into a shared library, once, into a cache directory.

``python -m sim_sitl.avr.build`` builds it (``scripts/setup.sh`` calls this) and prints its path. The library is
cached under ``$QUADLINK_CACHE_DIR`` or ``$XDG_CACHE_HOME/quadlink`` (``~/.cache/quadlink``), named by a hash of
the source and the compiler flags, so an edited shim is rebuilt and two worktrees never load each other's.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from quadlink.errors import QuadlinkError

SOURCE = Path(__file__).with_name("shim.c")
CFLAGS = ("-O2", "-shared", "-fPIC", "-std=gnu11", "-Wall", "-Wextra", "-Werror", "-Wno-unused-parameter")
LIBS = ("-lsimavr", "-lelf")


class ShimBuildError(QuadlinkError):
    """The simavr shim could not be compiled (missing gcc, libsimavr-dev or libelf-dev)."""


def cache_dir() -> Path:
    explicit = os.environ.get("QUADLINK_CACHE_DIR")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "quadlink"


def library_path() -> Path:
    digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(CFLAGS + LIBS).encode()).hexdigest()[:16]
    return cache_dir() / f"libquadlink_simavr-{digest}.so"


def build(force: bool = False) -> Path:
    """The shim's shared library, compiled now unless an identical one is cached."""
    out = library_path()
    if out.is_file() and not force:
        return out
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        raise ShimBuildError("no C compiler (gcc) to build the simavr shim: apt-get install gcc")
    if not Path("/usr/include/simavr/sim_avr.h").is_file():
        raise ShimBuildError("simavr headers missing: apt-get install libsimavr-dev libelf-dev")
    out.parent.mkdir(parents=True, exist_ok=True)
    # compile to a temporary name and rename: concurrent first uses (pytest workers) never load half a file
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [cc, *CFLAGS, "-o", tmp, str(SOURCE), *LIBS]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        Path(tmp).unlink(missing_ok=True)
        raise ShimBuildError(f"building the simavr shim failed ({' '.join(cmd)}):\n{proc.stderr.strip()}")
    os.replace(tmp, out)
    return out


def main() -> int:
    try:
        path = build(force="--force" in sys.argv[1:])
    except ShimBuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
