"""The demo's ground link over an impaired network (issue 18): the netem proxies between the ground station
and the companion, for both its MAVLink link (UDP) and the operator image stream (TCP).

The ground station sends to ``Ports.vehicle_netem`` (UDP) and reads images from ``Ports.image_netem`` (TCP);
the proxies forward to the companion's ``Ports.vehicle`` and ``Ports.image``. ``delay_ms`` is one way, in
each direction. The proxies run on wall time; in lock-step the simulation may run slower than real time,
so the delay the *vehicle dynamics* see is ``delay x real-time factor`` (the report states the factor).
Their counters go to ``link.json`` for the report (loss measured, not assumed).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import yaml

from harness.netem import Impairment, TcpProxy, UdpProxy, start_proxy
from quadlink import CONFIG_DIR


@dataclass(frozen=True)
class LinkImpairment:
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    seed: int = 0

    def impairment(self) -> Impairment:
        return Impairment(delay_ms=self.delay_ms, jitter_ms=self.jitter_ms, loss=self.loss)


class LinkProxies:
    """The two proxies of a demo flight; ``close()`` stops them, ``stats()`` their counters."""

    def __init__(self, link: LinkImpairment, listen_udp: int, target_udp: int, listen_tcp: int,
                 target_tcp: int) -> None:
        self.link = link
        imp = link.impairment()
        self.mavlink = start_proxy("udp", listen_udp, target_udp, imp, seed=link.seed)
        self.image = start_proxy("tcp", listen_tcp, target_tcp, imp, seed=link.seed + 1)

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {"impairment": asdict(self.link)}
        mav = self.mavlink
        if isinstance(mav, UdpProxy):
            for name, model in (("uplink", mav.uplink), ("downlink", mav.downlink)):
                s = model.stats
                out[name] = {"packets_in": s.packets_in, "released": s.released, "lost": s.dropped_loss,
                             "queue_drops": s.dropped_queue, "reordered": s.reordered,
                             "mean_delay_ms": s.mean_delay_s * 1e3,
                             "loss_fraction": s.dropped_loss / s.packets_in if s.packets_in else 0.0}
        if isinstance(self.image, TcpProxy):
            out["image_stream"] = {"kind": "tcp", "loss": "none (a byte stream: delay and jitter only)"}
        return out

    def close(self) -> None:
        self.mavlink.close()
        self.image.close()


def write_link_stats(out_dir: Path, proxies: LinkProxies) -> None:
    (out_dir / "link.json").write_text(json.dumps(proxies.stats(), indent=2) + "\n")


def teleop_config_with_passivity(out_dir: Path, enabled: bool) -> Path:
    """``configs/teleop.yaml`` with ``passivity.enabled`` set, written to the flight's folder."""
    cfg = yaml.safe_load((CONFIG_DIR / "teleop.yaml").read_text()) or {}
    cfg.setdefault("passivity", {})
    cfg["passivity"]["enabled"] = bool(enabled)
    path = out_dir / "teleop.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path
