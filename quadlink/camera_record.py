"""The camera record: the byte format of one RGB-D frame, its codec and its file recordings (no sockets).

Record format (the unit of the TCP camera stream, :mod:`quadlink.camera_stream`, and of a recording file)::

    record  = b"QLCF" | uint32 LE header_len | header (UTF-8 JSON) | rgb bytes | depth bytes
    header  = {"seq", "stamp_s", "width", "height", "intrinsics": {fx, fy, cx, cy},
               ["R_qc": 3x3 rows, "p_qc_m": [x, y, z],]
               "rgb_encoding": "rgb8" | "jpeg", "rgb_bytes": n, "depth_encoding": "mm_u16le" | "none",
               "depth_bytes": n, "meta": {...}}
    meta    = free-form on the sensor stream (SITL -> companion); on the companion's operator image stream it is
              quadlink.operator_image.OperatorImageMeta.to_wire(), decoded strictly by the ground station

A sensor record carries what a real driver gives: image, depth, stamp and the intrinsics the device reports. It
has **no mount**: where the camera sits on the vehicle is the reader's calibration (``configs/vehicle.yaml``), never
the producer's (the SITL's mount is a drawn truth the vehicle must not see). ``R_qc``/``p_qc_m`` appear only where
the producer *is* the vehicle and the reader needs its calibration: the companion's operator image stream
(``encode_record(..., with_mount=True)``). A header with any key outside this schema is refused.

Colour is RGB8 row-major (or JPEG); depth is uint16 little-endian millimetres, 0 = invalid. A header is
hostile input: :class:`RecordHeader` validates it before anything is allocated, and :class:`RecordDecoder`
is an I/O-free streaming decoder (feed bytes, get frames).
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera_frame import CameraIntrinsics, RgbdFrame
from quadlink.errors import ProtocolError

__all__ = ["DEPTH_ENCODINGS", "MAGIC", "MAX_HEADER_BYTES", "MAX_IMAGE_SIDE_PX", "MAX_PAYLOAD_BYTES",
           "RGB_ENCODINGS", "FrameRecordWriter", "RecordDecoder", "RecordHeader", "encode_record", "jpeg_size",
           "read_frame_recording"]

log = logging.getLogger(__name__)

MAGIC = b"QLCF"
_PREFIX = struct.Struct("<4sI")
MAX_HEADER_BYTES = 1 << 20
MAX_PAYLOAD_BYTES = 64 << 20


def encode_record(frame: RgbdFrame, rgb_jpeg: bool = False, jpeg_quality: int = 85, with_mount: bool = False) -> bytes:
    """Serialise a frame into one stream record (see module doc); ``with_mount`` adds the frame's ``R_qc``/``p_qc_m``
    (the vehicle's own calibration, for its operator image stream only)."""
    if rgb_jpeg:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            raise ProtocolError("JPEG encoding of the colour image failed")
        rgb_bytes = buf.tobytes()
    else:
        rgb_bytes = np.ascontiguousarray(frame.rgb, dtype=np.uint8).tobytes()
    if frame.depth_m is not None:
        depth_mm = np.clip(np.nan_to_num(frame.depth_m, nan=0.0) * 1000.0 + 0.5, 0, 65535).astype("<u2")
        depth_bytes = depth_mm.tobytes()
    else:
        depth_bytes = b""
    k = frame.intrinsics
    header = {
        "seq": int(frame.seq),
        "stamp_s": float(frame.stamp_s),
        "width": int(k.width),
        "height": int(k.height),
        "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy},
        "rgb_encoding": "jpeg" if rgb_jpeg else "rgb8",
        "rgb_bytes": len(rgb_bytes),
        "depth_encoding": "mm_u16le" if depth_bytes else "none",
        "depth_bytes": len(depth_bytes),
        "meta": frame.meta,
    }
    if with_mount:
        header["R_qc"] = np.asarray(frame.R_qc, dtype=float).tolist()
        header["p_qc_m"] = np.asarray(frame.p_qc_m, dtype=float).tolist()
    header_bytes = json.dumps(header, separators=(",", ":")).encode()
    return _PREFIX.pack(MAGIC, len(header_bytes)) + header_bytes + rgb_bytes + depth_bytes


MAX_IMAGE_SIDE_PX = 4096
#: every key a header may have (``R_qc``/``p_qc_m`` only on the vehicle's own operator image stream)
HEADER_KEYS = frozenset({"seq", "stamp_s", "width", "height", "intrinsics", "R_qc", "p_qc_m", "rgb_encoding",
                         "rgb_bytes", "depth_encoding", "depth_bytes", "meta"})
RGB_ENCODINGS = ("rgb8", "jpeg")
DEPTH_ENCODINGS = ("mm_u16le", "none")
_JPEG_SOF_MARKERS = frozenset((0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF))


@dataclass(frozen=True)
class RecordHeader:
    """A camera record's header, validated: every number finite and in range, every size consistent with the
    image it describes (issue 16: a header is hostile input; nothing is allocated before this check)."""

    seq: int
    stamp_s: float
    width: int
    height: int
    intrinsics: CameraIntrinsics
    R_qc: NDArray[np.float64] | None  # None: a sensor record (the reader's calibration places the camera)
    p_qc_m: NDArray[np.float64] | None
    rgb_encoding: str
    rgb_bytes: int
    depth_encoding: str
    depth_bytes: int
    meta: Any

    @classmethod
    def parse(cls, header: Any) -> RecordHeader:
        if not isinstance(header, dict):
            raise ProtocolError("camera record header is not a JSON object")
        unknown = sorted(set(header) - HEADER_KEYS)
        if unknown:
            raise ProtocolError(f"camera record header has fields outside the schema: {', '.join(map(str, unknown))}")
        if ("R_qc" in header) != ("p_qc_m" in header):
            raise ProtocolError("camera record header has one of R_qc, p_qc_m without the other")
        width = _header_int(header, "width", 1, MAX_IMAGE_SIDE_PX)
        height = _header_int(header, "height", 1, MAX_IMAGE_SIDE_PX)
        rgb_encoding = _header_choice(header, "rgb_encoding", RGB_ENCODINGS)
        depth_encoding = _header_choice(header, "depth_encoding", DEPTH_ENCODINGS)
        rgb_bytes = _header_int(header, "rgb_bytes", 0, MAX_PAYLOAD_BYTES)
        depth_bytes = _header_int(header, "depth_bytes", 0, MAX_PAYLOAD_BYTES)
        if rgb_encoding == "rgb8" and rgb_bytes != width * height * 3:
            raise ProtocolError(f"rgb_bytes {rgb_bytes} != {width}x{height}x3")
        if rgb_encoding == "jpeg" and rgb_bytes == 0:
            raise ProtocolError("empty JPEG colour image")
        expected_depth = width * height * 2 if depth_encoding == "mm_u16le" else 0
        if depth_bytes != expected_depth:
            raise ProtocolError(f"depth_bytes {depth_bytes} != {expected_depth} for "
                                f"{depth_encoding} {width}x{height}")
        k = header.get("intrinsics")
        if not isinstance(k, dict):
            raise ProtocolError("intrinsics missing")
        fx, fy, cx, cy = (_finite(k.get(name), f"intrinsics.{name}") for name in ("fx", "fy", "cx", "cy"))
        if not (fx > 0 and fy > 0):
            raise ProtocolError("focal lengths must be > 0")
        R_qc = p_qc_m = None
        if "R_qc" in header:
            R_qc = _finite_array(header.get("R_qc"), (3, 3), "R_qc")
            if not np.allclose(R_qc @ R_qc.T, np.eye(3), atol=1e-3):
                raise ProtocolError("R_qc is not a rotation")
            p_qc_m = _finite_array(header.get("p_qc_m"), (3,), "p_qc_m")
        return cls(
            seq=_header_int(header, "seq", 0, 2**63 - 1),
            stamp_s=_finite(header.get("stamp_s"), "stamp_s"),
            width=width, height=height,
            intrinsics=CameraIntrinsics(fx, fy, cx, cy, width, height),
            R_qc=R_qc, p_qc_m=p_qc_m,
            rgb_encoding=rgb_encoding, rgb_bytes=rgb_bytes, depth_encoding=depth_encoding, depth_bytes=depth_bytes,
            meta=header.get("meta"),
        )

    @property
    def payload_bytes(self) -> int:
        return self.rgb_bytes + self.depth_bytes


def _header_int(header: dict[str, Any], key: str, lo: int, hi: int) -> int:
    value = header.get(key)
    if isinstance(value, bool) or not isinstance(value, int):  # JSON's Infinity and 1e999 arrive as floats
        raise ProtocolError(f"{key} must be an integer, got {str(value)[:40]}")
    if not lo <= value <= hi:
        raise ProtocolError(f"{key} {value} out of range {lo}..{hi}")
    return value


def _header_choice(header: dict[str, Any], key: str, allowed: tuple[str, ...]) -> str:
    value = header.get(key)
    if value not in allowed:
        raise ProtocolError(f"unknown {key} {str(value)[:40]!r}")
    return str(value)


def _finite(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(f"{key} must be a finite number, got {str(value)[:40]}")
    return float(value)


def _finite_array(value: Any, shape: tuple[int, ...], key: str) -> NDArray[np.float64]:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ProtocolError(f"{key} is not a numeric array") from exc
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise ProtocolError(f"{key} must be finite with shape {shape}, got {array.shape}")
    return array


def jpeg_size(data: memoryview | bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame marker, read without decoding (so a 900-byte file that
    claims 30000x30000 is refused before the decoder allocates 2.7 GB)."""
    n = len(data)
    if n < 4 or data[0] != 0xFF or data[1] != 0xD8:
        raise ProtocolError("colour image is not a JPEG")
    i = 2
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise ProtocolError("corrupt JPEG marker")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = (data[i + 2] << 8) | data[i + 3]
        if length < 2:
            raise ProtocolError("corrupt JPEG segment length")
        if marker in _JPEG_SOF_MARKERS:
            if i + 9 > n:
                break
            height = (data[i + 5] << 8) | data[i + 6]
            width = (data[i + 7] << 8) | data[i + 8]
            return width, height
        i += 2 + length
    raise ProtocolError("JPEG has no frame header")


def _decode_body(head: RecordHeader, buf: bytearray, offset: int) -> RgbdFrame:
    """The frame whose images start at ``offset`` in ``buf`` (colour, then depth): each image is copied out of
    the buffer once, straight into its own array (the caller then drops the record from the buffer)."""
    width, height = head.width, head.height
    rgb_n = head.rgb_bytes
    if head.rgb_encoding == "jpeg":
        view = memoryview(buf)[offset:offset + rgb_n]
        try:
            if jpeg_size(view) != (width, height):
                raise ProtocolError(f"JPEG is {jpeg_size(view)}, header says {(width, height)}")
            bgr = cv2.imdecode(np.frombuffer(view, np.uint8), cv2.IMREAD_COLOR)
        finally:
            view.release()
        if bgr is None or bgr.shape != (height, width, 3):
            raise ProtocolError("JPEG colour image does not decode")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    else:
        rgb = np.frombuffer(buf, np.uint8, rgb_n, offset).reshape(height, width, 3).copy()
    depth: NDArray[np.float32] | None = None
    if head.depth_encoding == "mm_u16le":
        depth = np.frombuffer(buf, "<u2", head.depth_bytes // 2, offset + rgb_n).reshape(height, width)
        depth = depth.astype(np.float32)
        depth *= np.float32(1e-3)
    return RgbdFrame(
        seq=head.seq,
        stamp_s=head.stamp_s,
        rgb=np.asarray(rgb, dtype=np.uint8),
        depth_m=depth,
        intrinsics=head.intrinsics,
        R_qc=np.eye(3) if head.R_qc is None else head.R_qc,   # no mount: the camera source attaches its calibration
        p_qc_m=np.zeros(3) if head.p_qc_m is None else head.p_qc_m,
        meta=dict(head.meta or {}),
    )


def _framing_bytes(header: Any) -> int:
    """The payload size a header announces, which the stream's framing rests on (checked before anything else:
    a negative or non-integer size would make the decoder wait forever or never shrink its buffer)."""
    if not isinstance(header, dict):
        raise ProtocolError("camera record header is not a JSON object")
    return _header_int(header, "rgb_bytes", 0, MAX_PAYLOAD_BYTES) + \
        _header_int(header, "depth_bytes", 0, MAX_PAYLOAD_BYTES)


class RecordDecoder:
    """Streaming decoder of camera records: feed bytes, get whole frames.

    A corrupt record raises :class:`ProtocolError` (the stream has lost its framing; the caller
    reconnects). Sizes are bounded so a bad header cannot make it allocate without limit.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    @property
    def pending_bytes(self) -> int:
        """Bytes held of a record not complete yet."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[RgbdFrame]:
        self._buf += data
        frames = []
        while len(self._buf) >= _PREFIX.size:
            magic, header_len = _PREFIX.unpack_from(self._buf)
            if magic != MAGIC or header_len > MAX_HEADER_BYTES:
                self._buf.clear()
                raise ProtocolError("camera stream lost framing (bad magic or header length)")
            if len(self._buf) < _PREFIX.size + header_len:
                break
            try:
                header = json.loads(bytes(self._buf[_PREFIX.size:_PREFIX.size + header_len]))
                payload_bytes = _framing_bytes(header)
            except (ValueError, RecursionError, ProtocolError) as exc:  # UnicodeDecodeError is a ValueError
                self._buf.clear()  # the sizes cannot be trusted: the framing is lost
                raise ProtocolError(f"corrupt camera record header: {exc}") from exc
            start = _PREFIX.size + header_len
            end = start + payload_bytes
            if len(self._buf) < end:
                break
            try:  # the framing holds: a record with bad contents is dropped alone
                frame = _decode_body(RecordHeader.parse(header), self._buf, start)
            except (ValueError, TypeError, ProtocolError) as exc:
                raise ProtocolError(f"corrupt camera record: {exc}") from exc
            finally:
                del self._buf[:end]   # no view of the buffer outlives _decode_body (its arrays are copies)
            frames.append(frame)
        return frames


class FrameRecordWriter:
    """Appends frames to a file as camera-stream records (the wire format above, one after another), so a
    flight's camera can be replayed later (:func:`read_frame_recording`). Depth is stored as the stream
    carries it (uint16 mm), colour raw: about 380 kB per QVGA frame."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")   # noqa: SIM115 - held open for the whole run
        self.frames = 0

    def write(self, frame: RgbdFrame) -> None:
        self._f.write(encode_record(frame))
        self.frames += 1

    def close(self) -> None:
        self._f.close()


def read_frame_recording(path: str | Path, chunk_bytes: int = 1 << 20) -> Iterator[RgbdFrame]:
    """The frames of a file written by :class:`FrameRecordWriter` (or a raw dump of a camera stream).

    A truncated last record (the writer was killed) ends the iteration with a warning; a corrupt one
    raises :class:`ProtocolError`."""
    decoder = RecordDecoder()
    with open(path, "rb") as f:
        while chunk := f.read(chunk_bytes):
            yield from decoder.feed(chunk)
    if decoder.pending_bytes:
        log.warning("%s: %d bytes of an incomplete last record ignored", path, decoder.pending_bytes)
