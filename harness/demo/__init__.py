"""``quadlink demo``: orchestration of the whole stack in the SITL and the flight report (issue 8)."""

from harness.demo.cli import command

__all__ = ["command"]
