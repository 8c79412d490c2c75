"""The live view's door in front of foxglove-sdk's server: a viewer offering only the old
protocol name gets in under that name, one offering the SDK's name passes untouched, and
garbage or a half-open peer does not stop the next viewer."""

import asyncio
import json
import socket

import pytest
import websockets

from services.foxglove.door import OLD_NAME, SDK_NAME, SubprotocolDoor, offered_protocols, rename_protocol


@pytest.fixture
def door():
    import foxglove

    server = foxglove.start_server(name="door test", host="127.0.0.1", port=0)
    channel = foxglove.Channel("/viz/test", schema={"type": "object", "properties": {"n": {"type": "number"}}},
                               message_encoding="json")
    front = SubprotocolDoor("127.0.0.1", 0, server.port)
    yield front, channel
    front.close()
    server.stop()


async def first_messages(port: int, names: list[str], channel) -> tuple[str, list[str], dict]:
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=names, open_timeout=10) as ws:
        ops = []
        while "advertise" not in ops:
            ops.append(json.loads(await asyncio.wait_for(ws.recv(), 10))["op"])
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel.id()}]}))
        await asyncio.sleep(0.2)  # the subscription reaches the server
        channel.log(json.dumps({"n": 1.5}).encode())
        while isinstance(raw := await asyncio.wait_for(ws.recv(), 10), str):
            pass
        assert raw[0] == 0x01 and int.from_bytes(raw[1:5], "little") == 7  # messageData of subscription 7
        return ws.subprotocol, ops, json.loads(raw[13:])


@pytest.mark.parametrize("names", [[OLD_NAME], [SDK_NAME], [OLD_NAME, SDK_NAME]])
def test_a_viewer_gets_in_under_the_name_it_offered(door, names):
    front, channel = door
    chosen, ops, message = asyncio.run(first_messages(front.port, names, channel))
    assert chosen == (SDK_NAME if SDK_NAME in names else OLD_NAME)
    assert ops[0] == "serverInfo" and message == {"n": 1.5}
    assert front.renamed == (0 if SDK_NAME in names else 1)


def test_a_viewer_offering_neither_name_is_refused_by_the_server_itself(door):
    front, _ = door

    async def connect():
        await websockets.connect(f"ws://127.0.0.1:{front.port}", subprotocols=["foxglove.websocket.v2"],
                                 open_timeout=10)
    with pytest.raises(websockets.InvalidStatus) as refused:
        asyncio.run(connect())
    assert refused.value.response.status_code == 400


def test_garbage_and_an_endless_head_end_their_own_connection_only(door):
    front, channel = door
    with socket.create_connection(("127.0.0.1", front.port)) as junk:
        junk.sendall(b"\x00\xff" * 10000)  # no blank line within MAX_HEAD_BYTES
        junk.settimeout(5)
        assert junk.recv(100) == b""  # closed by the door
    with socket.create_connection(("127.0.0.1", front.port)) as early:
        early.sendall(b"GET / HTTP/1.1\r\n")  # and gone before the head ends
    chosen, _, message = asyncio.run(first_messages(front.port, [OLD_NAME], channel))
    assert chosen == OLD_NAME and message == {"n": 1.5}
    assert front.refused >= 1


def test_closing_the_door_ends_the_viewers_connections(door):
    front, _ = door

    async def watch():
        async with websockets.connect(f"ws://127.0.0.1:{front.port}", subprotocols=[OLD_NAME]) as ws:
            await asyncio.wait_for(ws.recv(), 10)
            asyncio.get_running_loop().call_later(0.2, front.close)
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await asyncio.wait_for(ws.recv(), 10)
    asyncio.run(watch())
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", front.port), timeout=2)


def test_only_the_protocol_header_is_renamed():
    head = (b"GET / HTTP/1.1\r\nHost: x\r\nX-Note: foxglove.websocket.v1\r\n"
            b"sec-websocket-protocol: a, foxglove.websocket.v1\r\n\r\n")
    assert offered_protocols(head) == ["a", OLD_NAME]
    renamed = rename_protocol(head, OLD_NAME, SDK_NAME)
    assert offered_protocols(renamed) == ["a", SDK_NAME]
    assert b"X-Note: foxglove.websocket.v1" in renamed and renamed.endswith(b"\r\n\r\n")
