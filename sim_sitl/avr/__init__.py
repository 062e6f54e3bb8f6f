"""The FlightCtrl binary in simavr: a C shim over libsimavr (``shim.c``), built on first use (``build.py``) and
driven through ctypes (``sim.py``) in whole chunks of cycles."""
