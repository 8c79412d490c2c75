"""An rmw_zenoh subscriber nobody here wrote (zenoh-ros2-sdk, ROBOTIS) watching the cell:
``python -m tests.services.ros2.sdk_judge PORT DOMAIN OUT.json``.  It subscribes to
/joint_states and /ft_sensor/wrench as a client of the Zenoh session at
tcp/127.0.0.1:PORT, says "subscribed" on stdout, and on SIGTERM writes what it received
(stamp and values of every message), the topics its graph query listed and the
/robot_description a late transient-local subscriber got, to OUT.json.

The SDK finds message definitions as .msg files (offline it cannot clone ROS 2's
repositories, and a missing file silently gives a wrong hash): they are written from
rosbags' definitions into a folder of its own first."""

from __future__ import annotations

import json
import os
import re
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

TYPES = ("sensor_msgs/msg/JointState", "geometry_msgs/msg/WrenchStamped", "std_msgs/msg/String")


def write_definitions(folder: Path) -> None:
    from services.ros2.types import typestore

    for msgtype in TYPES:
        text = typestore().generate_msgdef(msgtype, ros_version=2)[0]
        parts = re.split(r"\n=+\nMSG: ", text)
        names = [msgtype] + [p.split("\n", 1)[0] for p in parts[1:]]
        bodies = [parts[0]] + [p.split("\n", 1)[1] if "\n" in p else "" for p in parts[1:]]
        for name, body in zip(names, bodies):
            path = folder / name.split("/")[0] / "msg" / f"{name.split('/')[-1]}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body)


def liveliness_tokens(port: int, domain: int) -> list[str]:
    """The graph as ``ros2 node list`` asks for it: every liveliness token of the domain."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    with zenoh.open(config) as session:
        return sorted(str(reply.ok.key_expr) for reply in session.liveliness().get(f"@ros2_lv/{domain}/**",
                                                                                    timeout=2.0) if reply.ok)


def main(port: int, domain: int, out: Path) -> None:
    scratch = Path(tempfile.mkdtemp(prefix="sdk-judge-"))
    os.environ["ZENOH_ROS2_SDK_CACHE"] = str(scratch / "cache")  # never clones: nothing there to find
    os.environ["ZENOH_CONFIG_OVERRIDE"] = 'mode="client"'  # as rmw_zenoh is advised to join from outside
    write_definitions(scratch / "msgs")
    from zenoh_ros2_sdk import ROS2Subscriber, get_registry, get_topic_names_and_types

    get_registry(messages_dir=str(scratch / "msgs"))
    got = {"joint_states": [], "wrench": [], "robot_description": None, "topics": None}
    lock = threading.Lock()

    def ns(header) -> int:
        return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)

    def on_joints(m):
        with lock:
            got["joint_states"].append([ns(m.header), list(m.name), [float(x) for x in m.position]])

    def on_wrench(m):
        f, t = m.wrench.force, m.wrench.torque
        with lock:
            got["wrench"].append([ns(m.header), m.header.frame_id, [f.x, f.y, f.z, t.x, t.y, t.z]])

    common = dict(domain_id=domain, router_ip="127.0.0.1", router_port=port)
    # the SDK's client makes one connection attempt (connect/timeout_ms 0): a session not
    # yet listening, or a slow accept on a loaded machine, fails it; a client tries again
    for attempt in range(5):
        try:
            first = ROS2Subscriber("/joint_states", TYPES[0], on_joints, **common)
            break
        except Exception:  # noqa: BLE001 - zenoh.ZError "Unable to connect", the last one raised
            if attempt == 4:
                raise
            time.sleep(1.0)
    subs = [first, ROS2Subscriber("/ft_sensor/wrench", TYPES[1], on_wrench, **common)]
    print("subscribed", flush=True)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    # a late subscriber to the transient-local description, as rviz2 started after the cell
    late = []
    subs.append(ROS2Subscriber("/robot_description", TYPES[2], lambda m: late.append(m.data),
                               qos=":1:,1:,:,:,,", **common))
    got["topics"] = get_topic_names_and_types(timeout=2.0, **common)
    got["tokens"] = liveliness_tokens(port, domain)
    done.wait()
    for sub in subs:
        sub.close()
    with lock:
        got["robot_description"] = late[0] if late else None
        out.write_text(json.dumps(got))


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]))
