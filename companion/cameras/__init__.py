"""The companion's cameras behind one interface (:class:`~companion.cameras.base.CameraInput`), chosen by URL.

=====================  ==========================================================================
``tcp://HOST:PORT``     the SITL camera stream (:mod:`.stream`); acks each processed frame (lock-step)
``PATH`` / ``tum://PATH``  a TUM RGB-D folder replayed at its recorded pace (:mod:`.tum`)
``realsense://[WxH]``   an Intel RealSense (:mod:`.realsense`, needs pyrealsense2)
``openni://``           an OpenNI2 device, e.g. Asus Xtion (:mod:`.openni`, needs openni + runtime)
=====================  ==========================================================================

This package is the companion's camera edge: the only place that opens camera devices, sockets and
recorded folders for the flight stack.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraInput, CameraUnavailable
from companion.cameras.stream import StreamCamera
from companion.cameras.tum import TumReplayCamera

__all__ = ["CameraInput", "CameraUnavailable", "StreamCamera", "TumReplayCamera", "open_camera"]


def _resolution(text: str, url: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError as exc:
        raise CameraUnavailable(f"{url}: resolution must be WIDTHxHEIGHT (e.g. 640x480)") from exc
    return w, h


def open_camera(url: str, clock: Callable[[], float] = time.monotonic, R_qc: NDArray[np.float64] | None = None,
                p_qc_m: NDArray[np.float64] | None = None) -> CameraInput:
    """Open the camera a URL names (table above); ``R_qc``, ``p_qc_m`` are the mount for sensors without one."""
    if url.startswith("tcp://"):
        return StreamCamera(url, clock)
    if url.startswith("realsense://"):
        from companion.cameras.realsense import RealSenseCamera

        rest = url[len("realsense://"):]
        w, h = _resolution(rest, url) if rest else (640, 480)
        return RealSenseCamera(w, h, R_qc=R_qc, p_qc_m=p_qc_m)
    if url.startswith("openni://"):
        from companion.cameras.openni import OpenNI2Camera

        return OpenNI2Camera(R_qc=R_qc, p_qc_m=p_qc_m)
    folder = url[len("tum://"):] if url.startswith("tum://") else url
    if Path(folder).is_dir():
        return TumReplayCamera(folder, clock, R_qc=R_qc, p_qc_m=p_qc_m)
    raise CameraUnavailable(f"{url}: camera must be tcp://HOST:PORT (the SITL stream), a TUM-format folder, "
                            "realsense://[WxH] or openni://")
