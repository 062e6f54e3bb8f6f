"""harness.ports: the offsets and blocks the SITL tests fly on are free, reserved, and never handed out twice."""

from __future__ import annotations

import random
import socket

import pytest

from harness.ports import (
    DEFAULT_PORTS,
    MAX_OFFSET,
    PORT_SLOT_STRIDE,
    Ports,
    free_port_base,
    free_port_offset,
    offset_ports,
    port_is_free,
)

pytestmark = pytest.mark.unit


def test_offsets_are_free_distinct_and_below_the_ephemeral_range() -> None:
    rng = random.Random(4)
    offsets = [free_port_offset(slots=2, rng=rng) for _ in range(20)]
    ports = [p for o in offsets for p in offset_ports(o, 2)]
    assert len(set(ports)) == len(ports), "two allocations share a port"
    assert max(ports) < 32768 and all(o % PORT_SLOT_STRIDE == 0 and o <= MAX_OFFSET for o in offsets)
    assert Ports(offsets[0]).truth == DEFAULT_PORTS["truth"] + offsets[0]


def test_a_port_someone_listens_on_is_never_handed_out() -> None:
    """The first candidate has a listener on one of its ports: another offset is handed out, all of it free."""
    class ListenedFirst(random.Random):
        def __init__(self) -> None:
            super().__init__(0)
            self.calls = 0

        def randrange(self, *args: int) -> int:   # type: ignore[override]
            self.calls += 1
            return 300 if self.calls == 1 else super().randrange(*args)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        taken = DEFAULT_PORTS["truth"] + 300 * PORT_SLOT_STRIDE
        s.bind(("127.0.0.1", taken))
        assert not port_is_free(taken)
        rng = ListenedFirst()
        offset = free_port_offset(rng=rng)
        assert rng.calls >= 2 and offset != 300 * PORT_SLOT_STRIDE and taken not in offset_ports(offset)


def test_blocks_are_contiguous_free_and_distinct() -> None:
    rng = random.Random(5)
    a, b = free_port_base(24, rng), free_port_base(24, rng)
    assert abs(a - b) >= 24 and 20000 <= min(a, b) and max(a, b) + 24 <= 32768
    with pytest.raises(ValueError):
        free_port_offset(slots=0)
