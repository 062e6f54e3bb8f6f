"""The companion's MAVLink parameters (PARAM_* addressed to compid 191, and MAV_CMD_DO_SET_PARAMETER).

Two parts, so the protocol half can be replaced by a shared MAVLink parameter service without touching
the values:

* :class:`CompanionParams` — the values and their validation (pure): the pan-scan generator and the
  reference gains the daemon uses, read and changed by name.
* :func:`handle_param_message` — the PARAM_* protocol over a :class:`ParamStore` (pure: a message in,
  the replies out, as dialect message objects for the caller to send).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol

from companion.config import PanScanConfig, pan_scan_params
from companion.pan_scan import PanScanParams
from companion.reference import ReferenceParams
from quadlink.mavlink import mavlink

# index order is the wire's param_index (also MAV_CMD_DO_SET_PARAMETER param1)
PARAM_NAMES = ("PANSCAN_EN", "PANSCAN_AMP", "PANSCAN_OMEGA", "CMP_K_V", "CMP_K_PSI", "CMP_SAFE_DIST")


class ParamStore(Protocol):
    """What the parameter protocol needs: names in index order, values, and a validated set."""

    names: tuple[str, ...]

    def values(self) -> dict[str, float]: ...

    def set(self, name: str, value: float) -> bool: ...


class CompanionParams:
    """The companion's tunable values. ``set`` validates; a rejected value leaves everything unchanged."""

    names: tuple[str, ...] = PARAM_NAMES

    def __init__(self, pan_scan: PanScanConfig, reference: ReferenceParams) -> None:
        self._pan_scan_cfg = pan_scan
        self.scan: PanScanParams = pan_scan_params(pan_scan)
        self.reference: ReferenceParams = reference

    def values(self) -> dict[str, float]:
        s, r = self.scan, self.reference
        return {"PANSCAN_EN": 1.0 if s.enabled else 0.0, "PANSCAN_AMP": s.amplitude_rad_s,
                "PANSCAN_OMEGA": s.omega_rad_s,
                "CMP_K_V": r.k_v_m_s, "CMP_K_PSI": r.k_psi_rad_s, "CMP_SAFE_DIST": r.safe_distance_m}

    def set(self, name: str, value: float) -> bool:
        if name not in PARAM_NAMES or not math.isfinite(value):
            return False
        if name == "PANSCAN_EN":
            self.scan = dataclasses.replace(self.scan, enabled=value >= 0.5)
        elif name in ("PANSCAN_AMP", "PANSCAN_OMEGA"):
            if value < 0 or (name == "PANSCAN_OMEGA" and value == 0):
                return False
            amp = value if name == "PANSCAN_AMP" else self.scan.amplitude_rad_s
            omega = value if name == "PANSCAN_OMEGA" else self.scan.omega_rad_s
            cfg = dataclasses.replace(self._pan_scan_cfg, enabled=self.scan.enabled, amplitude_rad_s=amp,
                                      omega_rad_s=omega)
            self.scan = pan_scan_params(cfg)  # the response (eq. 5) depends on omega
        else:
            if value < 0:
                return False
            r, v = self.reference, float(value)
            if name == "CMP_K_V":
                self.reference = dataclasses.replace(r, k_v_m_s=v)
            elif name == "CMP_K_PSI":
                self.reference = dataclasses.replace(r, k_psi_rad_s=v)
            else:
                self.reference = dataclasses.replace(r, safe_distance_m=v)
        return True


def param_value_message(store: ParamStore, index: int) -> Any:
    name = store.names[index]
    return mavlink.MAVLink_param_value_message(name.encode(), float(store.values()[name]),
                                               mavlink.MAV_PARAM_TYPE_REAL32, len(store.names), index)


def _param_id(msg: Any) -> str:
    return msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""


def handle_param_message(store: ParamStore, msg: Any) -> tuple[list[Any], str | None]:
    """A PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET for this component: (the PARAM_VALUE replies,
    the name of the parameter it changed or None). Unknown names and rejected values get no reply (the
    ground station's retry times out, as with PX4)."""
    kind = msg.get_type()
    if kind == "PARAM_REQUEST_LIST":
        return [param_value_message(store, i) for i in range(len(store.names))], None
    if kind == "PARAM_REQUEST_READ":
        name = _param_id(msg)
        index = store.names.index(name) if name in store.names else msg.param_index
        return ([param_value_message(store, index)] if 0 <= index < len(store.names) else []), None
    if kind == "PARAM_SET":
        name = _param_id(msg)
        if name in store.names and store.set(name, msg.param_value):
            return [param_value_message(store, store.names.index(name))], name
    return [], None


def set_by_index(store: ParamStore, index: int, value: float) -> str | None:
    """MAV_CMD_DO_SET_PARAMETER (param1 = index): the name it changed, None if refused."""
    if not 0 <= index < len(store.names):
        return None
    name = store.names[index]
    return name if store.set(name, value) else None
