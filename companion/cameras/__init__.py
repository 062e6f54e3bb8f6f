"""The companion's cameras behind one interface (:class:`~companion.cameras.base.CameraInput`), chosen by URL.

======================================  ============================================================
``tcp://HOST:PORT``                      the SITL camera stream (:mod:`.stream`); acks each processed frame
``PATH`` / ``tum://PATH``                a TUM RGB-D folder replayed at its recorded pace (:mod:`.tum`)
``realsense://[SERIAL][?size=WxH]``      an Intel RealSense (:mod:`.realsense`, needs pyrealsense2)
``realsense://software?source=URL``      another camera's frames through pyrealsense2's software device
                                         (:mod:`.realsense_software`): the RealSense path without hardware
``openni://[URI]``                       an OpenNI2 device, e.g. Asus Xtion (:mod:`.openni`, needs openni +
                                         the OpenNI2 runtime); URI picks one device (default: any)
======================================  ============================================================

The CLI's shorthands ``realsense[:SERIAL]`` and ``openni[:URI]`` map to these URLs (:func:`camera_url`).
This package is the companion's camera edge: the only place that opens camera devices, sockets and
recorded folders for the flight stack.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal
from urllib.parse import parse_qs, urlsplit

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraInput, CameraUnavailable
from companion.cameras.stream import StreamCamera
from companion.cameras.tum import TumReplayCamera

__all__ = ["CameraInput", "CameraUnavailable", "StreamCamera", "TumReplayCamera", "camera_url", "is_device_url",
           "open_camera"]


def camera_url(spec: str) -> str:
    """The CLI's ``--camera``: ``realsense[:SERIAL]`` / ``openni[:URI]`` shorthands -> URLs; others unchanged."""
    for name in ("realsense", "openni"):
        if spec == name or spec.startswith(name + ":") and not spec.startswith(name + "://"):
            return f"{name}://{spec[len(name) + 1:]}"
    return spec


def is_device_url(url: str) -> bool:
    """A live sensor, whose stamps are its own clock (the companion maps them to its clock)."""
    return url.startswith("openni://") or (url.startswith("realsense://")
                                           and not url.startswith("realsense://software"))


def _resolution(text: str, url: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError as exc:
        raise CameraUnavailable(f"{url}: resolution must be WIDTHxHEIGHT (e.g. 640x480)") from exc
    return w, h


def open_camera(url: str, clock: Callable[[], float] = time.monotonic, R_qc: NDArray[np.float64] | None = None,
                p_qc_m: NDArray[np.float64] | None = None,
                stamps: Literal["local", "device"] = "local") -> CameraInput:
    """Open the camera a URL names (table above); ``R_qc``, ``p_qc_m`` are the vehicle's calibrated mount, which every
    source places its frames with (no sensor, simulated or real, reports where it is mounted);
    ``stamps`` is what a device camera does with its clock (``local``: mapped to ``clock``)."""
    if url.startswith("tcp://"):
        return StreamCamera(url, clock, R_qc=R_qc, p_qc_m=p_qc_m)
    if url.startswith("realsense://software"):
        from companion.cameras.realsense_software import SoftwareRealSenseCamera

        sources = parse_qs(urlsplit(url).query).get("source")
        if not sources:
            raise CameraUnavailable(f"{url}: a software RealSense needs ?source=URL (tum://PATH or tcp://HOST:PORT)")
        source = open_camera(sources[0], clock, R_qc, p_qc_m, stamps)
        return SoftwareRealSenseCamera(source, R_qc, p_qc_m, stamps, clock)
    if url.startswith("realsense://"):
        from companion.cameras.realsense import RealSenseCamera

        parts = urlsplit(url)
        size = parse_qs(parts.query).get("size")
        w, h = _resolution(size[0], url) if size else (640, 480)
        serial = (parts.netloc + parts.path).strip("/") or None
        return RealSenseCamera(w, h, serial=serial, R_qc=R_qc, p_qc_m=p_qc_m, stamps=stamps, clock=clock)
    if url.startswith("openni://"):
        from companion.cameras.openni import OpenNI2Camera

        return OpenNI2Camera(uri=url[len("openni://"):] or None, R_qc=R_qc, p_qc_m=p_qc_m, stamps=stamps,
                             clock=clock)
    folder = url[len("tum://"):] if url.startswith("tum://") else url
    if Path(folder).is_dir():
        return TumReplayCamera(folder, clock, R_qc=R_qc, p_qc_m=p_qc_m)
    raise CameraUnavailable(f"{url}: camera must be tcp://HOST:PORT (the SITL stream), a TUM-format folder, "
                            "realsense[:SERIAL], realsense://software?source=URL or openni[:URI]")
