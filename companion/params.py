"""The companion's MAVLink parameters (PARAM_* addressed to compid 191, and MAV_CMD_DO_SET_PARAMETER).

Two parts, so the protocol half can be replaced by a shared MAVLink parameter service without touching
the values:

* :data:`PARAM_SPECS` — the one table of the companion's parameters: name, unit, inclusive bounds (issue 16:
  an unbounded PANSCAN_AMP of 3e38 reached the setpoints; PANSCAN_OMEGA = 1e-40 made the pan-scan's yaw
  offset A/omega overflow float32 when TELEOP_FEEDBACK was packed).
* :class:`CompanionParams` — the values (pure): the pan-scan generator and the reference gains the daemon
  uses, read and changed by name, every change checked against the table.
* :func:`handle_param_message` — the PARAM_* protocol over a :class:`ParamStore` (pure: a message in,
  the replies out, as dialect message objects for the caller to send). A refused PARAM_SET is answered,
  as PX4 does, with PARAM_VALUE holding the unchanged value (the sender's retries end and it shows the
  truth) and a STATUSTEXT saying why.
* :class:`ParamService` — the ground-station side of both (pure): PARAM_* and MAV_CMD_DO_SET_PARAMETER over
  the values, each change announced by a STATUSTEXT; the replies returned as :mod:`companion.outbound` values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Protocol

from companion.config import PanScanConfig, pan_scan_params
from companion.modes import SEVERITY_INFO, StatusText
from companion.outbound import GcsReply
from companion.pan_scan import PanScanParams
from companion.reference_params import ReferenceParams
from quadlink.errors import ConfigError
from quadlink.mavlink import mavlink


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: wire name (<= 16 characters), unit, inclusive bounds; ``flag``: only 0 or 1."""

    name: str
    unit: str
    min: float
    max: float
    description: str
    flag: bool = False

    def refusal(self, value: float) -> str | None:
        """Why ``value`` cannot be stored, or None."""
        if not math.isfinite(value):
            return "not finite"
        if self.flag and value not in (0.0, 1.0):
            return "must be 0 or 1"
        if not self.min <= value <= self.max:
            return f"outside {self.min:g}..{self.max:g} {self.unit}".rstrip()
        return None


# index order is the wire's param_index (also MAV_CMD_DO_SET_PARAMETER param1)
PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("PANSCAN_EN", "", 0.0, 1.0, "pan-scan on (1) / off (0)", flag=True),
    # eq. (4): yaw-rate amplitude A; its yaw offset A/omega stays below 1.5/0.1 = 15 rad
    ParamSpec("PANSCAN_AMP", "rad/s", 0.0, 1.5, "pan-scan yaw-rate amplitude A (eq. 4)"),
    ParamSpec("PANSCAN_OMEGA", "rad/s", 0.1, 10.0, "pan-scan angular frequency omega (eq. 4)"),
    ParamSpec("CMP_K_V", "m/s", 0.0, 3.0, "horizontal speed at full handle deflection (eq. 2)"),
    ParamSpec("CMP_K_PSI", "rad/s", 0.0, 3.0, "yaw rate at full handle deflection (eq. 3)"),
    ParamSpec("CMP_SAFE_DIST", "m", 0.1, 3.0, "safe distance to obstacles (paper Fig. 8)"),
)
PARAM_NAMES = tuple(s.name for s in PARAM_SPECS)
SPECS_BY_NAME = {s.name: s for s in PARAM_SPECS}


class ParamStore(Protocol):
    """What the parameter protocol needs: names in index order, values, the reason a value is refused and
    a validated set."""

    names: tuple[str, ...]

    def values(self) -> dict[str, float]: ...

    def refusal(self, name: str, value: float) -> str | None: ...

    def set(self, name: str, value: float) -> bool: ...


class CompanionParams:
    """The companion's tunable values. ``set`` validates; a rejected value leaves everything unchanged.
    The configured starting values must lie inside the table's bounds too (ConfigError otherwise)."""

    names: tuple[str, ...] = PARAM_NAMES

    def __init__(self, pan_scan: PanScanConfig, reference: ReferenceParams) -> None:
        self._pan_scan_cfg = pan_scan
        self.scan: PanScanParams = pan_scan_params(pan_scan)
        self.reference: ReferenceParams = reference
        for name, value in self.values().items():
            why = self.refusal(name, value)
            if why is not None:
                raise ConfigError(f"companion config: {name} = {value!r} (from the pan_scan/reference keys): {why}")

    def values(self) -> dict[str, float]:
        s, r = self.scan, self.reference
        return {"PANSCAN_EN": 1.0 if s.enabled else 0.0, "PANSCAN_AMP": s.amplitude_rad_s,
                "PANSCAN_OMEGA": s.omega_rad_s,
                "CMP_K_V": r.k_v_m_s, "CMP_K_PSI": r.k_psi_rad_s, "CMP_SAFE_DIST": r.safe_distance_m}

    def refusal(self, name: str, value: float) -> str | None:
        spec = SPECS_BY_NAME.get(name)
        return "unknown parameter" if spec is None else spec.refusal(float(value))

    def set(self, name: str, value: float) -> bool:
        if self.refusal(name, value) is not None:
            return False
        v = float(value)
        if name == "PANSCAN_EN":
            self.scan = dataclasses.replace(self.scan, enabled=v == 1.0)
        elif name in ("PANSCAN_AMP", "PANSCAN_OMEGA"):
            amp = v if name == "PANSCAN_AMP" else self.scan.amplitude_rad_s
            omega = v if name == "PANSCAN_OMEGA" else self.scan.omega_rad_s
            cfg = dataclasses.replace(self._pan_scan_cfg, enabled=self.scan.enabled, amplitude_rad_s=amp,
                                      omega_rad_s=omega)
            self.scan = pan_scan_params(cfg)  # the response (eq. 5) depends on omega
        elif name == "CMP_K_V":
            self.reference = dataclasses.replace(self.reference, k_v_m_s=v)
        elif name == "CMP_K_PSI":
            self.reference = dataclasses.replace(self.reference, k_psi_rad_s=v)
        else:
            self.reference = dataclasses.replace(self.reference, safe_distance_m=v)
        return True


def param_value_message(store: ParamStore, index: int) -> Any:
    name = store.names[index]
    return mavlink.MAVLink_param_value_message(name.encode(), float(store.values()[name]),
                                               mavlink.MAV_PARAM_TYPE_REAL32, len(store.names), index)


def _param_id(msg: Any) -> str:
    raw = msg.param_id
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return raw.split("\x00", 1)[0] if isinstance(raw, str) else ""


def refusal_text(name: str, why: str) -> StatusText:
    """The STATUSTEXT (warning) that goes with a refused parameter change (sent whole, in chunks if long)."""
    return StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {name} refused: {why}")


def handle_param_message(store: ParamStore, msg: Any) -> tuple[list[Any | StatusText], str | None]:
    """A PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET for this component: (the replies, the name of
    the parameter it changed or None). A PARAM_SET with a bad value or ``param_type`` (not REAL32) is
    answered with the unchanged PARAM_VALUE and a STATUSTEXT; unknown names get no reply (a broadcast
    PARAM_SET of an autopilot parameter also reaches this component)."""
    kind = msg.get_type()
    if kind == "PARAM_REQUEST_LIST":
        return [param_value_message(store, i) for i in range(len(store.names))], None
    if kind == "PARAM_REQUEST_READ":
        name = _param_id(msg)
        index = store.names.index(name) if name in store.names else msg.param_index
        return ([param_value_message(store, index)] if 0 <= index < len(store.names) else []), None
    if kind == "PARAM_SET":
        name = _param_id(msg)
        if name not in store.names:
            return [], None
        index = store.names.index(name)
        why = f"param_type {msg.param_type}, expected REAL32" if msg.param_type != mavlink.MAV_PARAM_TYPE_REAL32 \
            else store.refusal(name, msg.param_value)
        if why is None and store.set(name, msg.param_value):
            return [param_value_message(store, index)], name
        return [param_value_message(store, index), refusal_text(name, why or "refused")], None
    return [], None


def set_by_index(store: ParamStore, index: int, value: float) -> str | None:
    """MAV_CMD_DO_SET_PARAMETER (param1 = index): the name it changed, None if refused."""
    if not 0 <= index < len(store.names):
        return None
    name = store.names[index]
    return name if store.set(name, value) else None


class ParamService:
    """The companion's parameters as the ground stations see them: the protocol over ``store`` (the values
    stay readable and replaceable there), and a STATUSTEXT (info) for every change, old and new value."""

    def __init__(self, store: ParamStore) -> None:
        self.store = store

    def _changed(self, name: str, old: float | None) -> StatusText:
        return StatusText(SEVERITY_INFO, f"companion: {name} {old:g} -> {self.store.values()[name]:g}")

    def on_message(self, msg: Any) -> list[StatusText | GcsReply]:
        """A PARAM_* message for this component (:func:`handle_param_message`): the change notice, then the
        replies."""
        before = self.store.values()
        replies, changed = handle_param_message(self.store, msg)
        out: list[StatusText | GcsReply] = [] if changed is None else [self._changed(changed, before[changed])]
        return out + [r if isinstance(r, StatusText) else GcsReply(r) for r in replies]

    def set(self, name: str, value: float) -> tuple[bool, list[StatusText | GcsReply]]:
        """Set ``name`` by name (not from a ground station): changed?, and the change notice."""
        old = self.store.values().get(name)
        if not self.store.set(name, value):
            return False, []
        return True, [self._changed(name, old)]

    def set_by_index(self, index: int, value: float) -> tuple[bool, list[StatusText | GcsReply]]:
        """MAV_CMD_DO_SET_PARAMETER: changed?, and the change notice and the value now (changed or not, as a
        refused PARAM_SET is answered; nothing for an index out of range)."""
        names = self.store.names
        old = self.store.values().get(names[index]) if 0 <= index < len(names) else None
        changed = set_by_index(self.store, index, value)
        out: list[StatusText | GcsReply] = [] if changed is None else [self._changed(changed, old)]
        if old is not None:
            out.append(GcsReply(param_value_message(self.store, index)))
        return changed is not None, out
