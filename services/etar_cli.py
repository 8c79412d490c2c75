"""The ``etar`` command line with MCAP recordings as demonstrations.

``etar`` (the console script) is ``etar.cli`` plus the ``.mcap`` loader from
``services.recording``: etar knows nothing of recordings, so the format is
registered here, one layer up.

    etar learn demo_000.mcap demo_001.mcap --phases auto --out model.json
"""

from __future__ import annotations

import sys

import etar.cli

from services.recording import load_demonstration


def main(argv=None) -> int:
    etar.cli.LOADERS[".mcap"] = lambda p: [load_demonstration(p)]
    return etar.cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
