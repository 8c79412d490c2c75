"""A Foxglove WebSocket client that subscribes to every channel a server advertises and
counts what arrives: the viewer a bench puts on the live view (bench/realtime_load.py
--foxglove), so the bridge does the work a watched run costs."""

from __future__ import annotations

import asyncio
import json
import threading
import time

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]  # the SDK's server takes the new name


class Viewer(threading.Thread):
    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.port = port
        self.stop = threading.Event()
        self.messages = 0
        self.bytes = 0
        self.error = None

    def run(self) -> None:
        try:
            asyncio.run(self._watch())
        except Exception as exc:  # noqa: BLE001 - reported by the bench
            self.error = f"{type(exc).__name__}: {exc}"

    async def _watch(self) -> None:
        import websockets

        deadline = time.monotonic() + 30
        while True:
            try:
                ws = await websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=SUBPROTOCOLS,
                                              max_size=None)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)
        async with ws:
            while not self.stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                except websockets.ConnectionClosedOK:
                    break  # the run ended and its bridge with it
                if isinstance(raw, str):
                    msg = json.loads(raw)
                    if msg["op"] == "advertise":
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": ch["id"], "channelId": ch["id"]} for ch in msg["channels"]]}))
                else:
                    self.messages += 1
                    self.bytes += len(raw)
