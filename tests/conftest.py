import zlib

import numpy as np
import pytest


@pytest.fixture
def rng(request):
    """A generator seeded from the test's name (printed, so a failure can be replayed)."""
    seed = zlib.crc32(request.node.name.encode())
    print(f"rng seed={seed}")
    return np.random.default_rng(seed)
