"""Issue 17: a SITL flight whose companion reads its camera as a RealSense: the SITL's frames go through the real
pyrealsense2 library (its software device: syncer, alignment, depth scale, intrinsics — the code path of a live
device) into `quadlink companion --camera realsense://software?source=tcp://...`. Take-off, hover, a push."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from flight_harness import MODE_TELEOP, flight

from harness.ports import free_port_offset
from quadlink.mavlink import mavlink

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(600),
              pytest.mark.skipif(importlib.util.find_spec("pyrealsense2") is None, reason="needs pyrealsense2")]

OFFSET = free_port_offset()   # harness.ports: free now, reserved for this session


def test_a_flight_on_the_realsense_path(tmp_path: Path) -> None:
    with flight(tmp_path, offset=OFFSET, camera="realsense://software?source=tcp://127.0.0.1:{port}") as f:
        f.take_off()  # returns once through 0.7 m of a climb to 1.0 m: the hover is judged after the climb
        f.run_for(3.0, lambda: f.manual(0))
        p0 = f.p_arena.copy()
        f.run_for(8.0, lambda: f.manual(0))
        drift_h = float(np.linalg.norm(f.p_arena[:2] - p0[:2]))
        height_m = -float(f.p_arena[2])
        print(f"hover: drift {drift_h:.3f} m horizontal, height {height_m:.3f} m (from {-p0[2]:.3f})")
        assert drift_h < 0.3, f"drifted {drift_h:.2f} m horizontally in an 8 s hover"
        # 1.0 m above the take-off point, where the body centre stands 0.1 m above the floor on its gear
        assert abs(height_m - 1.1) < 0.2, f"body centre hovered {height_m:.2f} m above the floor, not 1.1 m"
        assert f.mode == MODE_TELEOP and f.flags & mavlink.QUADLINK_TELEOP_FLAGS_ODOMETRY_OK, "odometry not ok"
        p1 = f.p_arena.copy()
        f.run_for(5.0, lambda: f.manual(600))
        moved = float(np.linalg.norm(f.p_arena[:2] - p1[:2]))
        assert moved > 0.6, f"moved {moved:.2f} m when pushed for 5 s"
        s = f.log.min_surface(0.0)
        assert s is not None and s.clearance.surface_m >= 0.40
