"""The ``etar`` command line with MCAP recordings as demonstrations.

``etar`` (the console script) is ``etar.cli`` plus the ``.mcap`` loader from
``services.recordings.demonstrations``: etar knows nothing of recordings, so the format is
registered here, one layer up.  A truncated recording (a recorder killed
mid-episode) is learned from with a warning that says what it lost: every
complete chunk of it is real data (``etar-bench recover`` makes it a finished file).

    etar learn demo_000.mcap demo_001.mcap --phases auto --out model.json
"""

from __future__ import annotations

import sys

import etar.cli

from services.recordings.demonstrations import load_demonstration


def load_recording(path) -> list[dict]:
    demo = load_demonstration(path, allow_incomplete=True)
    if not demo["complete"]:
        print(f"etar learn: warning: {path}: incomplete recording, learning from the {len(demo['states'])} samples "
              f"it kept (t {demo['t'][0]:.2f}..{demo['t'][-1]:.2f} s, robot cycles {demo['seq'][0]}..{demo['seq'][-1]}); "
              f"what came after is lost: {demo['problem']}", file=sys.stderr, flush=True)
    return [demo]


def main(argv=None) -> int:
    etar.cli.LOADERS[".mcap"] = load_recording
    return etar.cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
