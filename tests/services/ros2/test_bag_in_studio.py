"""A ROS 2 bag of ``etar-bench export --rosbag2`` opened in a real Foxglove: the open-source
Foxglove Studio 1.48 (``make foxglove-studio``) in headless chromium, driven as the
recording's own test drives it (tests/services/foxglove/test_foxglove_studio.py, whose
helpers this imports), with the layout for ROS 2 bags, docs/foxglove/ros2.layout.json.

The smoke reproduction's bag MCAP file (the ``ros2`` profile, CDR, ``ros2msg`` schemas) is
served with HTTP range requests and opened paused in the middle, then seeked while paused,
then played.  Checked from what the app says and shows: every topic of the bag listed with
its ROS 2 type as schema; no problem (the list empty, no badge) and no error in the 3D
panel's settings (a URDF that does not parse, a frame without a transform); the arm
(orange, its links' colour in the URDF) and the plates (grey) drawn in the 3D panel from
/robot_description and /tf paused, after the seek and playing, and the arm moving with
/tf between the two paused looks (from the panel's pixels); the force plot and the phase
row with data.  Studio 1.48 draws a URDF from a topic only from ``/robot_description``
(std_msgs/String, the name is fixed) and only when the 3D panel's ``topics`` setting has it
visible; the frames come from /tf (tf2_msgs/msg/TFMessage) whatever the settings.  The
screenshots stay in ``out/foxglove-studio/rosbag2/``.

What the checks tell apart (this VM): the bag as exported, orange 12 % and grey 7 % of the
panel, the arm's pixels 2.1 % changed between the two paused looks; the same bag without
/tf, the arm upright at the URDF's zero angles (orange still 5.7 %, changed 0 %); a URDF
with a link no joint reaches, or a visual without geometry, drawn or not but said only in
the panel's settings ("Missing transform from frame <nowhere> to frame <base>", "Failed to
parse URDF: ... <visual> must have geometry"), the problem list empty both times.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.cli import bench as bench_cli
from services.ros2.types import TOPICS
from tests.services.foxglove.test_foxglove_studio import (
    ARTIFACTS, ROOT, _files, coloured_share, grey_share, label_share, need_studio, open_in_studio, orange_share,
    rfc3339)

# a browser with software WebGL and fixed waits, after a smoke run: serial and slow
pytestmark = [pytest.mark.serial, pytest.mark.slow]

LAYOUT = ROOT / "docs" / "foxglove" / "ros2.layout.json"
OUT = ARTIFACTS / "rosbag2"


def orange_mask(png: Path) -> np.ndarray:
    """Where ``orange_share`` counts the arm's pixels."""
    from PIL import Image

    pixels = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)
    r, g, b = pixels[..., 0], pixels[..., 1], pixels[..., 2]
    ratio = g / np.maximum(r, 1.0)
    return (r > 120) & (r - b > 90) & (ratio > 0.3) & (ratio < 0.7)


def bag_contents(mcap_path: Path) -> tuple[dict, str, list]:
    """The bag's channels (topic: schema name), its profile, and the log times of /tf."""
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        profile = reader.get_header().profile
        summary = reader.get_summary()
        channels = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        tf_times = [m.log_time for _, _, m in reader.iter_messages(topics=["/tf"])]
    return channels, profile, tf_times


def test_foxglove_studio_draws_the_arm_of_an_exported_ros2_bag(foxglove_run_dir, tmp_path):
    need_studio()
    out = tmp_path / "rosbag2"
    assert bench_cli.main(["export", str(foxglove_run_dir), "--rosbag2", "--out", str(out)]) == 0
    bag = out / "reproduction_00" / "reproduction_00.mcap"
    channels, profile, tf_times = bag_contents(bag)
    assert profile == "ros2" and channels == {t.name: t.type for t in TOPICS}, (profile, channels)
    middle, later = tf_times[len(tf_times) // 2], tf_times[len(tf_times) * 3 // 4]

    files = _files()
    files["/layout.json"] = LAYOUT
    files["/data/reproduction_00.mcap"] = bag
    shown = open_in_studio(files, lambda base: {
        "url": f"{base}/?ds=remote-file&ds.url={base}/data/reproduction_00.mcap&layoutId=ros2&layoutName=ros2"
               f"&time={rfc3339(middle)}",
        "seek": f"{later / 1e9:.3f}", "out": str(OUT), "settingsOf": "3D!arm"})
    print("app's console warnings and errors:", *shown["warnings"], sep="\n  ")

    # every topic of the bag listed, with its ROS 2 type as the schema
    assert {t["topic"]: t["schema"] for t in shown["topics"]} == channels
    # no problem with the bag, and none in the 3D panel (the URDF parsed, every frame placed)
    assert shown["problems"] == [] and shown["problemBadge"] in ("", "0"), shown["problems"]
    assert shown["settingsErrors"] == [], shown["settingsErrors"]
    assert shown["paused"] and shown["seek"]["paused"]
    assert abs(float(shown["seek"]["shown"]) - later / 1e9) < 0.05, shown["seek"]

    # the arm (orange in the URDF) and the plates (grey) drawn paused, after the seek and playing
    shares = {}
    for tag in ("paused", "seeked", "playing"):
        image = Path(shown["shots"][f"{tag}-3d"])
        shares[tag] = (orange_share(image), grey_share(image), label_share(image))
        print(f"{tag}: orange {shares[tag][0]:.2%}, grey {shares[tag][1]:.2%}, labels {shares[tag][2]:.2%}")
        assert shares[tag][0] > 0.05, f"no arm in the 3D panel {tag}: {image}"
        assert shares[tag][1] > 0.02, f"no plates in the 3D panel {tag}: {image}"
        assert shares[tag][2] < 0.05, f"frame labels swamp the 3D panel {tag}: {image}"
    # the arm is posed by /tf, not the URDF's zero angles: it moved between the two paused looks
    moved = float(np.mean(orange_mask(Path(shown["shots"]["paused-3d"]))
                          != orange_mask(Path(shown["shots"]["seeked-3d"]))))
    print(f"arm's pixels changed between the middle and the seek: {moved:.3%}")
    assert moved > 0.0005, "the arm did not move between the middle and three quarters: /tf not applied?"
    # the force plot and the phase row have data
    plot = coloured_share(Path(shown["shots"]["paused-plot"]))
    phase = coloured_share(Path(shown["shots"]["paused-phase"]))
    print(f"plot coloured {plot:.2%}, phase row coloured {phase:.2%}")
    assert plot > 0.002
    assert phase > 0.01
