"""RGB-D frames and the local camera stream (SITL -> companion, companion -> operator view): the public names
of the camera modules, importable from here.

- :mod:`quadlink.camera_frame`: :class:`RgbdFrame` and :class:`CameraIntrinsics`;
- :mod:`quadlink.camera_record`: the record format (header, colour, depth), its validating codec
  (:func:`encode_record`, :class:`RecordDecoder`) and file recordings;
- :mod:`quadlink.camera_stream`: the TCP server and client, with the acknowledgements of lock-step.
"""

from __future__ import annotations

from quadlink.camera_frame import CameraIntrinsics, RgbdFrame
from quadlink.camera_record import (
    DEPTH_ENCODINGS,
    MAGIC,
    MAX_HEADER_BYTES,
    MAX_IMAGE_SIDE_PX,
    MAX_PAYLOAD_BYTES,
    RGB_ENCODINGS,
    FrameRecordWriter,
    RecordDecoder,
    RecordHeader,
    encode_record,
    jpeg_size,
    read_frame_recording,
)
from quadlink.camera_stream import CameraStreamClient, CameraStreamServer, parse_tcp_url

__all__ = ["DEPTH_ENCODINGS", "MAGIC", "MAX_HEADER_BYTES", "MAX_IMAGE_SIDE_PX", "MAX_PAYLOAD_BYTES",
           "RGB_ENCODINGS", "CameraIntrinsics", "CameraStreamClient", "CameraStreamServer", "FrameRecordWriter",
           "RecordDecoder", "RecordHeader", "RgbdFrame", "encode_record", "jpeg_size", "parse_tcp_url",
           "read_frame_recording"]
