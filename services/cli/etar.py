"""The ``etar`` command line with MCAP recordings as demonstrations.

``etar`` (the console script) is ``etar.cli`` plus the ``.mcap`` loader from
``services.recordings.demonstrations``: etar knows nothing of recordings, so the format is
registered here, one layer up.  ``etar learn`` refuses a recording whose metadata says it
is not a demonstration (a reproduction) before it loads any file.  A truncated recording
(a recorder killed mid-episode) is learned from with a warning that says what it lost:
every complete chunk of it is real data (``etar-bench recover`` makes it a finished file).

    etar learn demo_000.mcap demo_001.mcap --phases auto --out model.json
"""

from __future__ import annotations

import sys

import etar.cli

from services.recordings.demonstrations import load_demonstration
from services.recordings.reader import recording_kind


def load_recording(path) -> list[dict]:
    demo = load_demonstration(path, allow_incomplete=True)
    if not demo["complete"]:
        demo["warning"] = (f"{path}: incomplete recording, learning from the {len(demo['states'])} samples it kept "
                           f"(t {demo['t'][0]:.2f}..{demo['t'][-1]:.2f} s, robot cycles "
                           f"{demo['seq'][0]}..{demo['seq'][-1]}); what came after is lost: {demo['problem']}")
    return [demo]


def main(argv=None) -> int:
    etar.cli.LOADERS[".mcap"] = load_recording
    etar.cli.EPISODE_KINDS[".mcap"] = recording_kind
    return etar.cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
