"""The live relay's frame reading and its one repair (host/publish/ws_frames.py).

Frames are made by an independent implementation, the ``websockets`` library's own
(`websockets.frames.Frame.serialize`); the repair is driven on a simulated clock with exact counts,
then end to end: a WebSocket server of ``websockets`` in foxglove-sdk's place that answers the first
subscribe with the SDK's "Unknown channel ID" error, the relay, and the npm client under node."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import threading

import pytest
from websockets.frames import Frame, Opcode

from host.publish.live import SDK_SUBPROTOCOL, SubprotocolRelay
from host.publish.ws_frames import RETRIES, RETRY_DELAY_S, FrameStream, SubscribeRepair, text_frame
from tests.host.publish.test_live_node import CLIENT_JS, NODE_MODULES, _node


def _frame(opcode, data: bytes, *, mask: bool, fin: bool = True) -> bytes:
    return Frame(opcode, data, fin=fin).serialize(mask=mask)


@pytest.mark.parametrize("mask", [False, True])
def test_text_frames_come_out_whole_and_everything_else_passes_in_order(mask):
    texts = [b'{"op":"status"}', b"x" * 200, b"y" * 70_000]  # 7-bit, 16-bit and 64-bit lengths
    binary = bytes(range(256)) * 300
    stream = (_frame(Opcode.TEXT, texts[0], mask=mask) + _frame(Opcode.BINARY, binary, mask=mask)
              + _frame(Opcode.TEXT, texts[1], mask=mask) + _frame(Opcode.PING, b"p", mask=mask)
              + _frame(Opcode.TEXT, texts[2], mask=mask)
              + _frame(Opcode.TEXT, b"part", mask=mask, fin=False) + _frame(Opcode.CONT, b"rest", mask=mask))
    for step in (1, 7, 4096, len(stream)):  # however the bytes are cut up
        fs = FrameStream()
        got = []
        for i in range(0, len(stream), step):
            got += fs.feed(stream[i:i + step])
        assert b"".join(raw for _, raw in got) == stream  # nothing lost, nothing reordered
        assert [t for t, _ in got if t is not None] == texts  # a fragmented text is not inspected
        assert fs.at_boundary


def test_a_frame_cut_in_its_header_waits_for_the_rest():
    fs = FrameStream()
    whole = _frame(Opcode.TEXT, b"a" * 300, mask=True)
    assert fs.feed(whole[:3]) == [] and not fs.at_boundary
    assert fs.feed(whole[3:]) == [(b"a" * 300, whole)] and fs.at_boundary


def test_a_compressed_text_frame_passes_through_uninspected():
    raw = bytes([0x80 | 0x40 | 0x1, 2]) + b"zz"  # FIN, RSV1 (compressed), text; by hand: websockets
    # serializes RSV1 only through its extension
    got = FrameStream().feed(raw)
    assert all(t is None for t, _ in got) and b"".join(r for _, r in got) == raw


def test_a_text_over_the_limit_passes_through_uninspected():
    fs = FrameStream(max_text=10)
    whole = _frame(Opcode.TEXT, b"b" * 11, mask=False)
    got = fs.feed(whole)
    assert all(t is None for t, _ in got) and b"".join(r for _, r in got) == whole


def _parse(raw: bytes, *, mask: bool) -> Frame:
    """One frame of ``raw`` read by websockets' own parser (``mask``: it must be masked)."""
    from websockets.streams import StreamReader

    reader = StreamReader()
    reader.feed_data(raw)
    reader.feed_eof()
    parser = Frame.parse(reader.read_exact, mask=mask)
    try:
        next(parser)
    except StopIteration as done:
        return done.value
    raise AssertionError("incomplete frame")


def test_our_subscribe_frame_reads_back_in_an_independent_parser():
    for text in ('{"op":"subscribe"}', "z" * 300, "w" * 70_000):
        frame = _parse(text_frame(text), mask=True)  # a server expects a client's frame masked
        assert frame.opcode == Opcode.TEXT and frame.fin and frame.data == text.encode()


def _status(ch: int) -> bytes:
    return json.dumps({"op": "status", "level": 2, "message": f"Unknown channel ID: {ch}"}).encode()


def test_a_subscribe_answered_unknown_is_sent_again_with_growing_waits():
    r = SubscribeRepair()
    assert r.from_server(b'{"op":"advertise","channels":[{"id":5,"topic":"/a"},{"id":6,"topic":"/b"}]}', 0.0)
    r.from_client(b'{"op":"subscribe","subscriptions":[{"id":0,"channelId":5},{"id":1,"channelId":6}]}')
    assert r.from_server(_status(5), 1.0) is False  # held back
    assert r.take_due(1.0 + RETRY_DELAY_S / 2) == []
    (again,) = r.take_due(1.0 + RETRY_DELAY_S)
    assert json.loads(_parse(again, mask=True).data) == {
        "op": "subscribe", "subscriptions": [{"id": 0, "channelId": 5}]}
    t = 2.0
    for k in range(1, RETRIES):
        assert r.from_server(_status(5), t) is False
        assert r.next_due() == pytest.approx(t + RETRY_DELAY_S * 2 ** k)
        assert len(r.take_due(t + RETRY_DELAY_S * 2 ** k)) == 1
        t += 1.0
    assert r.resubscribed == RETRIES
    assert r.from_server(_status(5), t) is True and r.given_up == 1  # then the error is passed on


@pytest.mark.parametrize("why", ["never advertised", "never subscribed", "unsubscribed", "unadvertised"])
def test_an_unknown_channel_the_client_has_no_claim_to_is_passed_on(why):
    r = SubscribeRepair()
    if why != "never advertised":
        r.from_server(b'{"op":"advertise","channels":[{"id":5,"topic":"/a"}]}', 0.0)
    if why != "never subscribed":
        r.from_client(b'{"op":"subscribe","subscriptions":[{"id":3,"channelId":5}]}')
    if why == "unsubscribed":
        r.from_client(b'{"op":"unsubscribe","subscriptionIds":[3]}')
    if why == "unadvertised":
        r.from_server(b'{"op":"unadvertise","channelIds":[5]}', 0.0)
    assert r.from_server(_status(5), 1.0) is True and r.resubscribed == 0 and r.due == []


def test_other_server_text_and_bad_json_pass():
    r = SubscribeRepair()
    for text in (b"not json", b"[1,2]", b'{"op":"serverInfo"}', b'{"op":"status","message":"other"}'):
        assert r.from_server(text, 0.0) is True
        r.from_client(text)
    assert r.due == [] and r.subscriptions == {}


def _fake_sdk_server(log: list):
    """A WebSocket server in foxglove-sdk's place: advertises channel 7, answers the first
    subscribe with the SDK's error, and sends 3 messages once a subscribe is placed."""
    from websockets.sync.server import serve

    def handler(ws):
        ws.send(json.dumps({"op": "serverInfo", "name": "fake", "capabilities": []}))
        ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": 7, "topic": "/x", "encoding": "json", "schemaName": "x", "schema": "{}"}]}))
        for msg in ws:
            doc = json.loads(msg)
            log.append(doc)
            if doc.get("op") != "subscribe":
                continue
            if len(log) == 1:
                ws.send(json.dumps({"op": "status", "level": 2, "message": "Unknown channel ID: 7"}))
                continue
            sub = doc["subscriptions"][0]["id"]
            for k in range(3):
                ws.send(struct.pack("<BIQ", 1, sub, k) + json.dumps({"k": k}).encode())

    # no permessage-deflate, as foxglove-sdk (the npm client offers it)
    server = serve(handler, "127.0.0.1", 0, subprotocols=[SDK_SUBPROTOCOL], compression=None)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def test_through_the_relay_the_npm_client_gets_a_channel_the_server_first_called_unknown():
    node = _node()
    log: list = []
    server = _fake_sdk_server(log)
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.socket.getsockname()[1]))
    try:
        out = subprocess.run([node, str(CLIENT_JS), f"ws://localhost:{relay.port}", json.dumps(["/x"]), "3", "20"],
                             capture_output=True, text=True, timeout=60,
                             env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
    finally:
        relay.stop()
        server.shutdown()
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert out.returncode == 0, (doc["errors"], out.stderr, log)
    assert len(doc["messages"]["/x"]) == 3
    assert doc["resubscribed"] == []  # the client never saw the error: the relay sent the subscribe again
    assert [d["op"] for d in log] == ["subscribe", "subscribe"] and log[0] == log[1]
    assert relay.resubscribed == 1 and relay.unknown_channels_passed == 0
