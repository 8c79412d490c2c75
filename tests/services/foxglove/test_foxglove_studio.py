"""A recording opened in a real Foxglove: the open-source Foxglove Studio 1.48 (the app
``@foxglove/studio-base`` 1.48.0 ships prebuilt, ``make foxglove-studio``) in headless
chromium, with the committed layout, opened paused in the middle of a smoke
reproduction served with HTTP range requests; then a seek while paused, then playing.
Checked from what the app says and shows: every topic of the recording listed, the
visual ones with their Foxglove schemas; no problem reported; the arm and the world drawn
in the 3D panel paused, after the seek and playing, its frame labels small (from the
panel's pixels); the force plot and the phase rows with data.  And the same app watching a
run live through the bridge.  The screenshots stay in ``out/foxglove-studio/``.  Against a recording and the layout of fc0d2b4 (before issue 26)
the same checks fail: two problems (the schemas of /runner/event and /robot/episode), the
arm and the world gone when paused (orange 0.03 % and grey 0.5 % of the panel, against
15 % and 4.5 % now), labels' boxes over 28 % of it.
"""

from __future__ import annotations

import datetime
import http.server
import json
import os
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.recordings.reader import read_episode
from services.runtime.visual_topics import SCHEMA_NAMES

# a browser with software WebGL and fixed waits: serial (make test runs these one at a time)
pytestmark = [pytest.mark.serial]

ROOT = Path(__file__).resolve().parents[3]
STUDIO = ROOT / ".cache" / "foxglove-studio"
PAGE = ROOT / "tests" / "foxglove" / "studio"
ARTIFACTS = ROOT / "out" / "foxglove-studio"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def _files() -> dict:
    assets = STUDIO / "studio-base" / "package" / "assets"
    umd = STUDIO / "node_modules"
    return {"/": PAGE / "index.html", "/index.html": PAGE / "index.html", "/loader.js": PAGE / "loader.js",
            "/layout.json": ROOT / "docs" / "foxglove" / "etar.layout.json",
            "/react.production.min.js": umd / "react" / "umd" / "react.production.min.js",
            "/react-dom.production.min.js": umd / "react-dom" / "umd" / "react-dom.production.min.js",
            "assets": assets}


class _Handler(http.server.BaseHTTPRequestHandler):
    """The page, the app's files and the recording, with HTTP range requests (the app
    reads an MCAP file by ranges, and refuses a server that does not offer them)."""

    files: dict = {}

    def do_GET(self):  # the name http.server calls
        path = self.path.split("?", 1)[0]
        if path.startswith("/studio/"):
            file = self.files["assets"] / path[len("/studio/"):]
        else:
            file = self.files.get(path)
        if file is None or not Path(file).is_file() or ".." in path:
            self.send_error(404)
            return
        data = Path(file).read_bytes()
        types = {".html": "text/html", ".js": "text/javascript", ".json": "application/json",
                 ".wasm": "application/wasm", ".mcap": "application/octet-stream"}
        start, end, status = 0, len(data) - 1, 200
        found = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", ""))
        if found:
            first, last = found.groups()
            start, end = (int(first), min(int(last or end), end)) if first else (len(data) - int(last), end)
            status = 206
        self.send_response(status)
        self.send_header("Content-Type", types.get(Path(file).suffix, "application/octet-stream"))
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("Content-Length", str(end - start + 1))
        if status == 206:
            self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
        self.end_headers()
        try:
            self.wfile.write(data[start:end + 1])
        except (BrokenPipeError, ConnectionResetError):
            pass  # the app cancels range reads it no longer needs (a seek, the page closing)

    def log_message(self, format, *args):  # the signature http.server calls
        pass


def orange_share(png: Path) -> float:
    """The share of orange pixels, however the viewer's light shades the arm's colour."""
    from PIL import Image

    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)
    r, g, b = pixels[..., 0], pixels[..., 1], pixels[..., 2]
    ratio = g / np.maximum(r, 1.0)
    return float(np.mean((r > 120) & (r - b > 90) & (ratio > 0.3) & (ratio < 0.7)))


def grey_share(png: Path) -> float:
    """The share of lit grey pixels (the plates, shaded by the viewer's light), neither the
    dark background nor a coloured line."""
    from PIL import Image

    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.int32)
    grey = pixels.max(axis=-1) - pixels.min(axis=-1) < 20
    return float(np.mean(grey & (pixels.mean(axis=-1) > 110) & (pixels.mean(axis=-1) < 235)))


def label_share(png: Path) -> float:
    """The share of the frame labels' black boxes (the viewer draws a label white on black):
    at its default 0.2 m they covered a quarter of the panel."""
    from PIL import Image

    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.int32)
    return float(np.mean(np.all(pixels < 8, axis=-1)))


def coloured_share(png: Path) -> float:
    """The share of saturated pixels: a plot's lines, a state row's bars (the background
    and the text are grey)."""
    from PIL import Image

    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.int32)
    return float(np.mean(pixels.max(axis=-1) - pixels.min(axis=-1) > 80))


def rfc3339(ns: int) -> str:
    t = datetime.datetime.fromtimestamp(ns // 1_000_000_000, tz=datetime.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%S") + f".{ns % 1_000_000_000:09d}Z"


@pytest.fixture
def reproduction(foxglove_run_dir):
    return foxglove_run_dir / "recordings" / "reproduction_00.mcap"


def need_studio():
    if not (STUDIO / "READY").exists():
        pytest.skip(f"{STUDIO} is missing: `make foxglove-studio` (part of `make test`) installs Foxglove "
                    "Studio 1.48 from npm")
    if not Path(CHROMIUM).exists() or shutil.which("node") is None:
        pytest.skip("chromium or node is missing (`make browser` installs chromium as root)")


def serve(files: dict) -> tuple[http.server.ThreadingHTTPServer, str]:
    handler = type("Handler", (_Handler,), {"files": files})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


def drive(args: dict) -> subprocess.Popen:
    return subprocess.Popen(["node", str(PAGE / "drive.mjs"), json.dumps(args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, STUDIO_NODE_MODULES=str(STUDIO / "node_modules"), CHROMIUM=CHROMIUM))


def open_in_studio(files: dict, args_at) -> dict:
    """Serve ``files``, drive the app with ``args_at(base_url)`` (its screenshots' folder
    emptied first) and return what it showed."""
    server, base = serve(files)
    args = args_at(base)
    shutil.rmtree(args["out"], ignore_errors=True)
    try:
        proc = drive(args)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        server.shutdown()
    assert proc.returncode == 0, stderr[-3000:]
    return json.loads(stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_foxglove_studio_shows_a_reproduction_paused_after_a_seek_and_playing(reproduction):
    need_studio()
    episode = read_episode(reproduction)
    times = sorted(m.log_time_ns for m in episode.messages if m.topic == "/robot/state")
    middle, later = times[len(times) // 2], times[len(times) * 3 // 4]
    recorded = {m.topic for m in episode.messages}
    files = _files()
    files["/data/reproduction_00.mcap"] = reproduction
    shown = open_in_studio(files, lambda base: {
        "url": f"{base}/?ds=remote-file&ds.url={base}/data/reproduction_00.mcap&layoutId=etar&time={rfc3339(middle)}",
        "seek": f"{later / 1e9:.3f}", "out": str(ARTIFACTS / "recording")})
    listed = {t["topic"]: t["schema"] for t in shown["topics"]}
    # every topic recorded is listed, the visual ones with the schema Foxglove draws them by
    assert recorded <= set(listed), recorded - set(listed)
    for topic, schema in SCHEMA_NAMES.items():
        assert listed[topic] == schema, topic
    assert shown["problems"] == [] and shown["problemBadge"] in ("", "0"), shown["problems"]
    assert shown["paused"] and shown["seek"]["paused"]
    assert abs(float(shown["seek"]["shown"]) - later / 1e9) < 0.05, shown["seek"]
    # the arm (orange) and the world (grey plates) drawn paused, after the seek and playing
    for tag in ("paused", "seeked", "playing"):
        image = Path(shown["shots"][f"{tag}-3d"])
        # the arm is orange in the MuJoCo model (robot_sim.world.tasks), the world light grey
        assert orange_share(image) > 0.05, f"no arm in the 3D panel {tag}: {image}"
        assert grey_share(image) > 0.02, f"no world in the 3D panel {tag}: {image}"
        assert label_share(image) < 0.05, f"frame labels swamp the 3D panel {tag}: {image}"
    # the force plot and the phase rows have data
    assert coloured_share(Path(shown["shots"]["paused-plot"])) > 0.002
    assert coloured_share(Path(shown["shots"]["paused-phase"])) > 0.01


@pytest.mark.slow
@pytest.mark.zenoh
def test_foxglove_studio_watches_a_live_run_through_the_bridge(tmp_path):
    """Studio 1.48's live connection offers only ``foxglove.websocket.v1``; the bridge's door
    lets it in.  The app is opened first, at the port the run will serve (it retries a
    connection), then a lockstep run with the live view starts (lockstep: the browser's
    software WebGL takes a core, which a realtime run on two cores cannot spare).  The run
    must outlast the app's look: once it ends, the bridge closes and the app lists
    "Connection failed" (this VM, 10 s held: the app connected 8.8 s after it loaded in one
    run, and looked after the run's end in another, the run over 23 s after loading).  So
    the run holds up to 20 s simulated, and the test stops its episode (the robot's ``stop``,
    as a runner does at its deadline) once the app has looked: 26 s of a 44 s test were
    the run going on after the look."""
    from services.transport.launch import free_port
    from tests import support

    need_studio()
    port = free_port()
    server, base = serve(_files())
    out = ARTIFACTS / "live"
    shutil.rmtree(out, ignore_errors=True)
    proc = drive({"url": f"{base}/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:{port}&layoutId=etar",
                  "out": str(out), "live": {"timeout_ms": 60000, "topics": len(SCHEMA_NAMES), "draw_ms": 2000}})
    runner = support.runner(support.hold(20, {"clock": "lockstep"}), tmp_path / "run", foxglove=port,
                            run_id=f"studio-live-{int(time.time() * 1000)}")
    ran: dict = {}

    def run():
        try:
            ran["report"] = runner.run()
        except BaseException as exc:  # noqa: BLE001 - said by the test's assertion below
            ran["error"] = exc

    thread = threading.Thread(target=run, daemon=True)

    def reproducing() -> bool:
        try:  # a settle (episode -1) is the runner's own: only the reproduction is stopped
            return runner.cell is not None and runner.cell.request("robot", "status", timeout=2.0)["episode"] >= 0
        except (TimeoutError, RuntimeError):
            return False

    def stop_the_episode():
        support.wait_until(lambda: not thread.is_alive() or reproducing(), 60, "the reproduction under way",
                           poll_s=0.2)
        if thread.is_alive():
            runner.cell.request("robot", "stop", timeout=10.0)
        thread.join(120)

    try:
        t0 = time.monotonic()
        assert proc.stdout.readline().strip() == "LOADED", proc.stderr.read()[-3000:] if proc.poll() else ""
        print(f"app loaded after {time.monotonic() - t0:.1f} s")
        thread.start()
        stdout, stderr = proc.communicate(timeout=120)
        print(f"app closed after {time.monotonic() - t0:.1f} s")
        stop_the_episode()
        print(f"run over after {time.monotonic() - t0:.1f} s")
    finally:
        proc.kill()
        if thread.is_alive():
            stop_the_episode()
        server.shutdown()
    assert "report" in ran, f"the run raised: {ran.get('error')!r}"
    report = ran["report"]
    assert report["error"] is None, report["error"]
    assert proc.returncode == 0, stderr[-3000:]
    shown = json.loads(stdout.strip().splitlines()[-1])
    print(f"the app listed the topics {shown['listedAfterMs'] / 1e3:.1f} s after it loaded")
    # the app got in under the old name and lists every visual topic with its schema
    assert report["timing"]["services"]["foxglove_bridge"]["viewers_by_old_name"] >= 1
    assert {t["topic"]: t["schema"] for t in shown["topics"]} == SCHEMA_NAMES
    assert shown["problems"] == [], shown["problems"]
    image = Path(shown["shots"]["live-3d"])
    assert orange_share(image) > 0.05, f"no arm in the live 3D panel: {image}"
    assert grey_share(image) > 0.02, f"no world in the live 3D panel: {image}"
