"""Software in the loop: the virtual sheet on the C reference firmware (``chip_factory``) sends what
it sends on the Python chip model, frame for frame (only INFO's firmware version differs)."""

from __future__ import annotations

import pytest

from protocol.can import to_can
from protocol.framing import StreamDecoder, encode
from protocol.messages import GetInfo, Info, Sync
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet


def session(factory, transport, packed):
    sheet = VirtualSheet("gaussian", "5x5", noise=0.05, seed=4, chip_factory=factory, transport=transport,
                         fd=packed and transport == "can")
    gw = Gateway(sheet, packed=packed)
    wire = to_can if transport == "can" else encode
    gw.power_on(0.0)
    out = gw.pop_output(0.0)
    gw.receive(wire(GetInfo(0)), 0.1) if transport == "can" else gw.feed(wire(GetInfo(0)), 0.1)
    gw.commission(0.2)
    for i in range(30):
        now = 0.3 + 0.01 * i
        gw.receive(wire(Sync(counter=i)), now) if transport == "can" else gw.feed(wire(Sync(counter=i)), now)
        gw.poll(now)
    out += gw.pop_output(2.0)
    if transport == "serial":
        return StreamDecoder().feed(b"".join(out))
    from protocol.can import decode_can
    return [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in out]


@pytest.mark.parametrize("transport,packed", [("serial", False), ("serial", True), ("can", False), ("can", True)])
def test_c_firmware_chips_answer_like_the_model(transport, packed):
    chip_mod = pytest.importorskip("firmware_ref.chip")
    py = session(None, transport, packed)
    c = session(chip_mod.CFirmwareChip, transport, packed)
    assert len(py) == len(c) > 30
    for a, b in zip(py, c):
        if isinstance(a, Info):
            assert (a.node, a.capabilities, a.state) == (b.node, b.capabilities, b.state)
        else:
            assert a == b
