"""``quadlink netem``: an impaired UDP (MAVLink) or TCP (byte stream) link between two endpoints."""

from __future__ import annotations

import logging
import signal
import threading

import click

from harness.netem import Impairment, TcpProxy, UdpProxy, parse_endpoint
from quadlink.errors import ConfigError
from quadlink.signals import STOP_SIGNALS

log = logging.getLogger(__name__)


@click.command(help="Put delay, jitter, loss, reordering and a rate limit between two endpoints. "
               "UDP is bidirectional (replies go back to the last sender); TCP applies delay/jitter/rate to "
               "chunks (loss and reorder do not apply to a byte stream). --delay-ms is one-way, each direction.")
@click.option("--listen", "listen_url", required=True, help="udp:HOST:PORT or tcp:HOST:PORT to accept on.")
@click.option("--to", "to_url", required=True, help="udp:HOST:PORT or tcp:HOST:PORT to forward to.")
@click.option("--delay-ms", type=float, default=0.0, show_default=True, help="One-way mean delay.")
@click.option("--jitter-ms", type=float, default=0.0, show_default=True, help="Delay standard deviation (normal).")
@click.option("--jitter-correlation-s", type=float, default=0.0, show_default=True,
              help="Correlation time of the jitter (a queue building up); 0 = independent per packet.")
@click.option("--loss", type=float, default=0.0, show_default=True, help="Drop probability per datagram (UDP).")
@click.option("--reorder", type=float, default=0.0, show_default=True,
              help="Probability that a datagram is held back --reorder-gap-ms and overtaken (UDP).")
@click.option("--reorder-gap-ms", type=float, default=25.0, show_default=True)
@click.option("--rate-kbit", type=float, default=0.0, show_default=True, help="Link rate, kbit/s; 0 = unlimited.")
@click.option("--seed", type=int, default=None, help="Seed of the impairments (reproducible drops and delays).")
@click.option("--log-period-s", type=float, default=5.0, show_default=True, help="Forwarding statistics period.")
def command(listen_url: str, to_url: str, delay_ms: float, jitter_ms: float, jitter_correlation_s: float,
            loss: float, reorder: float,
            reorder_gap_ms: float, rate_kbit: float, seed: int | None, log_period_s: float) -> None:
    kind, host, port = parse_endpoint(listen_url)
    to_kind, to_host, to_port = parse_endpoint(to_url)
    if kind != to_kind:
        raise ConfigError(f"netem: --listen is {kind} but --to is {to_kind}")
    if log_period_s <= 0:
        raise ConfigError("netem: --log-period-s must be > 0")
    imp = Impairment(delay_ms=delay_ms, jitter_ms=jitter_ms, jitter_correlation_s=jitter_correlation_s,
                     loss=loss, reorder=reorder,
                     reorder_gap_ms=reorder_gap_ms, rate_kbit_s=rate_kbit)
    proxy: UdpProxy | TcpProxy
    if kind == "udp":
        proxy = UdpProxy((host, port), (to_host, to_port), imp, seed=seed, log_period_s=log_period_s)
    else:
        proxy = TcpProxy((host, port), (to_host, to_port), imp, seed=seed, log_period_s=log_period_s)
    log.info("netem %s %s:%d -> %s:%d: delay %.1f ms, jitter %.1f ms, loss %.3f, reorder %.3f, rate %s, seed %s",
             kind, *proxy.listen_address, to_host, to_port, delay_ms, jitter_ms, loss, reorder,
             f"{rate_kbit:g} kbit/s" if rate_kbit > 0 else "unlimited", seed)
    stopped = threading.Event()
    for sig in STOP_SIGNALS:   # Ctrl-C too (quadlink.signals)
        signal.signal(sig, lambda *_: stopped.set())
    proxy.start()
    try:
        while not stopped.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        proxy.close()
        log.info("netem: stopped")
