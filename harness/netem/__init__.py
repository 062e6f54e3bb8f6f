"""Network impairment between any two parts of the stack (issue 18): delay, jitter, loss, reorder, rate.

* :mod:`harness.netem.model` — the pure, seeded model (packets in, release times out) and a delay line;
* :mod:`harness.netem.udp` — the MAVLink UDP proxy (bidirectional, replies to the last sender);
* :mod:`harness.netem.tcp` — the byte-stream proxy (operator image stream; no loss/reorder on TCP);
* :mod:`harness.netem.cli` — ``quadlink netem``.

To put a link between two local ports from code (the demo does this)::

    from harness.netem import Impairment, start_proxy
    proxy = start_proxy("udp", listen_port=14556, target_port=14555,
                        impairment=Impairment(delay_ms=150, jitter_ms=30, loss=0.05), seed=1)
    ...  # the ground station sends to 14556, the companion listens on 14555
    proxy.close()

``delay_ms`` is one-way and applies in each direction (the round trip is twice it).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

from harness.netem.model import DelayLine, Impairment, ImpairmentModel, ImpairmentStats
from harness.netem.tcp import TcpProxy
from harness.netem.udp import UdpProxy
from quadlink.errors import ConfigError

__all__ = ["DelayLine", "Impairment", "ImpairmentModel", "ImpairmentStats", "TcpProxy", "UdpProxy",
           "parse_endpoint", "start_proxy"]


def parse_endpoint(text: str) -> tuple[Literal["udp", "tcp"], str, int]:
    """``udp:HOST:PORT`` or ``tcp:HOST:PORT`` -> (scheme, host, port); ConfigError naming the bad part."""
    scheme, _, rest = text.partition(":")
    host, _, port_text = rest.rpartition(":")
    if scheme not in ("udp", "tcp") or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ConfigError(f"netem: {text!r} is not udp:HOST:PORT or tcp:HOST:PORT")
    return ("udp" if scheme == "udp" else "tcp"), host, int(port_text)


def start_proxy(kind: Literal["udp", "tcp"], listen_port: int, target_port: int, impairment: Impairment,
                seed: int | None = None, host: str = "127.0.0.1", log_period_s: float = 5.0) -> UdpProxy | TcpProxy:
    """Start an impaired link ``host:listen_port`` -> ``host:target_port`` in a thread; ``.close()`` stops it.

    For ``tcp`` the loss and reorder of ``impairment`` are set to 0 (they do not apply to a byte stream).
    ``listen_port=0`` picks a free port (read ``.listen_address``).
    """
    if kind == "udp":
        return UdpProxy((host, listen_port), (host, target_port), impairment, seed=seed,
                        log_period_s=log_period_s).start()
    if kind == "tcp":
        return TcpProxy((host, listen_port), (host, target_port), replace(impairment, loss=0.0, reorder=0.0),
                        seed=seed, log_period_s=log_period_s).start()
    raise ConfigError(f"netem: unknown link kind {kind!r} (udp or tcp)")
