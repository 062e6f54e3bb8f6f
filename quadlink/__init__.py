"""quadlink: the shared core of the stack (CLI, configuration, links, MAVLink dialect, frames).

The flight roles live in the sibling top-level packages: ``sim_sitl``, ``firmware_bridge``,
``perception``, ``companion`` and ``teleop``.
"""

from pathlib import Path

__version__ = "0.1.0"

#: Repository root when installed in editable mode (the README's install); holds ``configs/``.
REPO_ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO_ROOT / "configs"
