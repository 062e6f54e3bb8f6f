"""The MK-Quadro serial protocol, defined once for the bridge and the SITL's firmware.

* :mod:`quadlink.mk.protocol`: framing (I/O-free codec, stream decoder);
* :mod:`quadlink.mk.fields`: field scalings and saturation shared by the structs;
* :mod:`quadlink.mk.standard`: MikroKopter's standard commands;
* :mod:`quadlink.mk.messages`: the stack's firmware messages (IMU, setpoint, status) and the dispatch;
* :mod:`quadlink.mk.flags`: flight state, status and error flags (IntEnum/IntFlag).

``PROTOCOL.md`` beside these modules documents the wire format with test vectors.
"""
