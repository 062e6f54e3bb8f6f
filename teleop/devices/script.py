"""Scripted operator for the virtual device: a YAML list of steps (configs/teleop_scripts/*.yaml).

    name: push toward the obstacle
    steps:
      - wait_s: 2                                   # hands off for 2 s
      - button: arm                                 # a press (instantaneous)
      - push: forward                               # forward|backward|left|right|sideways|up|down
        force_n: 2.0
        duration_s: 3.0
      - release: true                               # hands off
        duration_s: 1.0
      - force_d_n: [1.0, 0.5, 0.0]                  # any force in D (NED: x forward, y right, z down)
        duration_s: 2.0

Each step starts when the previous one ends; a ``button`` step takes no time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from quadlink.config import load_config
from quadlink.errors import ConfigError

ButtonName = Literal["arm", "disarm", "takeoff", "land", "pan_scan_on", "pan_scan_off", "pan_scan_toggle", "quit"]
Direction = Literal["forward", "backward", "left", "right", "sideways", "up", "down"]

#: unit vectors in D (NED)
DIRECTIONS_D: dict[str, tuple[float, float, float]] = {
    "forward": (1.0, 0.0, 0.0), "backward": (-1.0, 0.0, 0.0), "right": (0.0, 1.0, 0.0),
    "sideways": (0.0, 1.0, 0.0), "left": (0.0, -1.0, 0.0), "up": (0.0, 0.0, -1.0), "down": (0.0, 0.0, 1.0),
}


@dataclass(frozen=True)
class ScriptStepConfig:
    wait_s: float | None = None
    button: ButtonName | None = None
    push: Direction | None = None
    force_n: float | None = None
    force_d_n: tuple[float, float, float] | None = None
    release: bool = False
    duration_s: float | None = None


@dataclass(frozen=True)
class ScriptConfig:
    steps: list[ScriptStepConfig]
    name: str = ""


@dataclass(frozen=True)
class ForceSegment:
    start_s: float
    end_s: float
    force_d_n: tuple[float, float, float]


@dataclass(frozen=True)
class OperatorScript:
    """The timeline of a script: force segments and button presses, times from the script start."""

    name: str
    segments: tuple[ForceSegment, ...]
    presses: tuple[tuple[float, str], ...]
    end_s: float

    def force_at(self, t_s: float) -> NDArray[np.float64]:
        for seg in self.segments:
            if seg.start_s <= t_s < seg.end_s:
                return np.array(seg.force_d_n)
        return np.zeros(3)

    def presses_between(self, t0_s: float, t1_s: float) -> tuple[str, ...]:
        """Presses in (t0, t1]; a press at exactly 0 belongs to the first poll (t0 < 0)."""
        return tuple(name for t, name in self.presses if t0_s < t <= t1_s)


def _step_error(source: str, i: int, message: str) -> ConfigError:
    return ConfigError(f"{source}: key 'steps[{i}]': {message}")


def build_script(cfg: ScriptConfig, source: str = "<script>") -> OperatorScript:
    t = 0.0
    segments: list[ForceSegment] = []
    presses: list[tuple[float, str]] = []
    for i, step in enumerate(cfg.steps):
        kinds = [k for k, on in (("wait_s", step.wait_s is not None), ("button", step.button is not None),
                                 ("push", step.push is not None), ("force_d_n", step.force_d_n is not None),
                                 ("release", step.release)) if on]
        if len(kinds) != 1:
            raise _step_error(source, i, f"exactly one of wait_s, button, push, force_d_n, release per step "
                                         f"(got {', '.join(kinds) or 'none'})")
        kind = kinds[0]
        if kind == "button":
            presses.append((t, str(step.button)))
            continue
        if kind == "wait_s":
            duration = float(step.wait_s)  # type: ignore[arg-type]
            force = (0.0, 0.0, 0.0)
        else:
            if step.duration_s is None:
                raise _step_error(source, i, f"'{kind}' needs duration_s")
            duration = step.duration_s
            if kind == "push":
                if step.force_n is None:
                    raise _step_error(source, i, "'push' needs force_n")
                unit = DIRECTIONS_D[str(step.push)]
                force = (unit[0] * step.force_n, unit[1] * step.force_n, unit[2] * step.force_n)
            elif kind == "force_d_n":
                force = step.force_d_n  # type: ignore[assignment]
            else:
                force = (0.0, 0.0, 0.0)
        if duration < 0 or not np.isfinite(duration):
            raise _step_error(source, i, f"duration must be >= 0, got {duration}")
        if not np.all(np.isfinite(force)):
            raise _step_error(source, i, "force must be finite")
        segments.append(ForceSegment(t, t + duration, force))
        t += duration
    return OperatorScript(cfg.name, tuple(segments), tuple(presses), t)


def load_script(path: str | Path) -> OperatorScript:
    """Read and validate a script file; ConfigError naming the file and the step on bad input."""
    cfg = load_config(path, ScriptConfig)
    return build_script(cfg, str(path))
