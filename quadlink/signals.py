"""The signals every long-running quadlink command stops cleanly on (Ctrl-C and a supervisor's SIGTERM).

Both are installed explicitly: a process started in the background by a non-interactive shell inherits SIGINT
as ignored, and Python then raises no KeyboardInterrupt for it (a test's or a supervisor's Ctrl-C would not
stop the daemon).
"""

from __future__ import annotations

import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
