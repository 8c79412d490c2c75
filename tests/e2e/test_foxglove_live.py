"""The live view: a WebSocket client speaking Foxglove's protocol connects to a smoke run
over Zenoh (`etar-bench run --foxglove`) and receives the advertised visual channels and
their messages; and the live view changes nothing the run records or does."""

import pytest
import asyncio
import json
import re
import struct
import threading
import time

import websockets

from services.foxglove.scene import FRAMES
from services.recordings.reader import recorded_content
from services.runtime.visual_topics import SCHEMA_NAMES
from tests import support

# a whole run (or the service processes) over Zenoh: the slow lane
pytestmark = [pytest.mark.slow, pytest.mark.zenoh]
# the one wire format under its two names: the SDK's, and the only one Foxglove Studio
# 1.48 and the ws-protocol clients offer (let in by the bridge's door)
NAMES = ("foxglove.sdk.v1", "foxglove.websocket.v1")


def reproduction_scenario():
    """The smoke reproduction with the stored model, lockstep, ending at its goal."""
    return support.hold(15, {"clock": "lockstep", "reproduce.stop_at_goal": True})


async def watch(port: int, until: threading.Event, name: str) -> dict:
    """Connect offering only the protocol name ``name``, subscribe to every advertised
    channel, count what arrives until ``until``."""
    ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[name], max_size=None,
                                  open_timeout=20)
    seen = {"subprotocol": ws.subprotocol, "ops": [], "channels": {}, "messages": {}, "first": {}}
    async with ws:
        while not until.is_set():
            try:
                raw = await asyncio.wait_for(ws.recv(), 0.5)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
            if isinstance(raw, str):
                msg = json.loads(raw)
                seen["ops"].append(msg["op"])
                if msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        seen["channels"][ch["id"]] = ch
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": ch["id"], "channelId": ch["id"]} for ch in msg["channels"]]}))
                continue
            assert raw[0] == 0x01, raw[:1]  # messageData
            sub, log_time = struct.unpack_from("<IQ", raw, 1)
            topic = seen["channels"][sub]["topic"]
            seen["messages"][topic] = seen["messages"].get(topic, 0) + 1
            seen["first"].setdefault(topic, json.loads(raw[13:]))
    return seen


def test_a_foxglove_client_watches_a_live_run_which_records_what_it_would_have_without(tmp_path):
    scenario = reproduction_scenario()
    lines, done, result = [], threading.Event(), {}

    def say(line):
        lines.append(line)

    def go():
        try:
            result["report"] = support.run(scenario, tmp_path / "live", progress=say, foxglove=0,
                                           run_id=f"fg-{int(time.time() * 1000)}")
        finally:
            done.set()

    thread = threading.Thread(target=go)
    thread.start()
    try:
        def said_port():
            m = next((re.search(r"connect Foxglove to ws://127\.0\.0\.1:(\d+)", ln) for ln in list(lines)
                      if "connect Foxglove" in ln), None)
            return int(m.group(1)) if m else (-1 if done.is_set() else None)
        port = support.wait_until(said_port, 90, "the run names its live view's port", poll_s=0.05, seen=lambda: lines[-3:])
        assert port > 0, lines


        async def both():
            return await asyncio.gather(*(watch(port, done, name) for name in NAMES))
        views = dict(zip(NAMES, asyncio.run(both())))
    finally:
        thread.join(120)
    report = result["report"]
    assert report["error"] is None, report["error"]
    for name, seen in views.items():
        assert seen["subprotocol"] == name and seen["ops"][0] == "serverInfo", (name, seen["ops"][:3])
        advertised = {ch["topic"]: (ch["schemaName"], ch["encoding"], ch["schemaEncoding"])
                      for ch in seen["channels"].values()}
        assert advertised == {t: (schema, "json", "jsonschema") for t, schema in SCHEMA_NAMES.items()}, name
        assert all(seen["messages"].get(t, 0) >= 20 for t in ("/viz/tf", "/viz/scene", "/viz/status")), \
            (name, seen["messages"])
        assert [t["child_frame_id"] for t in seen["first"]["/viz/tf"]["transforms"]] == list(FRAMES)
    bridge = report["timing"]["services"]["foxglove_bridge"]
    assert bridge["sent"] > 0 and bridge["errors"] == 0
    assert bridge["viewers_by_old_name"] == 1, bridge

    # the same run without the live view, in one process: the same recording, the same result
    plain = support.run(scenario, tmp_path / "plain", transport="inproc", run_id="fg-plain")
    assert recorded_content(tmp_path / "live") == recorded_content(tmp_path / "plain")
    for key in ("final_position", "peak_contact_force", "reason", "sim_seconds"):
        assert report["reproductions"][0][key] == plain["reproductions"][0][key], key
