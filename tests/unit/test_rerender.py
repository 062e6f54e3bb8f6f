"""``quadlink rerender``: a flight's camera re-rendered along its truth finds what the scene holds and flags what
it does not (the tool that found the renderer's edge-on phantom, round 3)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from harness.rerender_cli import Rerenderer, command, every, read_truth
from quadlink.frames import R_from_quat_wxyz
from sim_sitl.truth import TruthEncoder

pytestmark = pytest.mark.unit

# two true poses of a demo flight in paper-arena (local NED from the start, attitude [w, x, y, z]): in the open
# (1.9 m from any wall or object) and facing the column 0.66 m away
OPEN = (30.0, [-0.061, -0.041, -1.069], [0.2342, -0.0004, 0.0016, -0.9722])
AT_COLUMN = (63.6, [2.439, -0.085, -1.041], [0.9796, -0.0017, 0.0055, -0.201])


def write_flight(folder: Path, poses: list[tuple[float, list[float], list[float]]]) -> Path:
    """A flight folder as the demo leaves it: flight.json and the SITL's truth log (its own encoder)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "flight.json").write_text(json.dumps({"scenario": "paper-arena", "sitl_config": None}))
    enc = TruthEncoder()
    with open(folder / "truth.tlog", "wb") as f:
        for t_s, p, q in poses:
            for packet in enc.encode(t_s, np.array(p), np.zeros(3), R_from_quat_wxyz(np.array(q)), np.zeros(3), 1.0,
                                     1.0):
                f.write(struct.pack(">Q", int(t_s * 1e6)) + packet)
    return folder


def test_truth_is_read_in_time_order_and_thinned(tmp_path: Path) -> None:
    folder = write_flight(tmp_path / "f", [(t, OPEN[1], OPEN[2]) for t in np.arange(0.0, 1.0, 0.02)])
    poses = read_truth(folder / "truth.tlog")
    assert len(poses) == 50 and poses[-1].t_s == pytest.approx(0.98)
    assert np.allclose(poses[0].R_ned_q, R_from_quat_wxyz(np.array(OPEN[2])), atol=1e-6)
    picked = [p.t_s for p in every(poses, 0.1, 0.5, 0.1)]
    assert picked == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])


def test_the_column_is_found_where_it_is_and_an_injected_surface_is_a_phantom(tmp_path: Path) -> None:
    folder = write_flight(tmp_path / "f", [OPEN, AT_COLUMN])
    poses = read_truth(folder / "truth.tlog")
    rr = Rerenderer(folder, seed=1)
    try:
        at_column = rr.frame(poses[1], near_m=1.2)
        assert at_column.seen_m.size > 5 and 0.55 < at_column.seen_m.min() < 0.8
        assert at_column.phantoms(0.2) == 0 and at_column.seen_surface_m.max() < 0.1
        in_the_open = rr.frame(poses[0], near_m=1.2)
        assert in_the_open.seen_m.size == 0 and in_the_open.phantoms(0.2) == 0
        # a renderer that draws a surface 0.8 m ahead where there is none (a fault injected after it)
        render = rr.camera.render

        def with_a_ghost(*args, **kwargs):   # type: ignore[no-untyped-def]
            frame = render(*args, **kwargs)
            h, w = frame.depth_m.shape
            frame.depth_m[h // 3:h // 2, w // 3:2 * w // 3] = 0.8
            return frame

        rr.camera.render = with_a_ghost      # type: ignore[method-assign]
        ghost = rr.frame(poses[0], near_m=1.2)
        assert ghost.seen_m.size > 0 and ghost.phantoms(0.2) > 0
    finally:
        rr.close()


def test_the_command_reports_a_clean_flight_and_refuses_a_folder_without_truth(tmp_path: Path) -> None:
    folder = write_flight(tmp_path / "f", [AT_COLUMN])
    res = CliRunner().invoke(command, [str(folder), "--from", "60", "--to", "70"])
    assert res.exit_code == 0, res.output
    assert "1 frames re-rendered; 0 with a phantom" in res.output and "in band: seen" in res.output
    (tmp_path / "empty").mkdir()
    res = CliRunner().invoke(command, [str(tmp_path / "empty")])
    assert res.exit_code != 0 and "truth.tlog" in str(res.exception or res.output)
