import zlib

import numpy as np
import pytest


@pytest.fixture
def rng(request):
    """A generator seeded from the test's name (printed, so a failure can be replayed)."""
    seed = zlib.crc32(request.node.name.encode())
    print(f"rng seed={seed}")
    return np.random.default_rng(seed)


def _weight(item) -> int:
    """How early a test's module goes to a worker: compose, then the runs over Zenoh, then
    the other slow ones, then the rest."""
    if item.get_closest_marker("compose"):
        return 0
    slow = item.get_closest_marker("slow") is not None
    if slow and item.get_closest_marker("zenoh"):
        return 1
    return 2 if slow else 3


def pytest_collection_modifyitems(config, items):
    """In an xdist worker: the modules that hold the longest tests first, so that with
    ``--dist loadscope --no-loadscope-reorder`` (make test) the two workers start on them
    and the quick ones fill the end.  xdist's own order (most tests first) sent the
    modules of one or two whole runs, compose among them, last: one worker ran them alone
    while the other had finished.  And everywhere: a test marked ``alone`` is marked
    ``serial`` too (make test's shared lane takes every test that is not serial)."""
    for item in items:
        if item.get_closest_marker("alone") and not item.get_closest_marker("serial"):
            raise pytest.UsageError(f"{item.nodeid} is marked alone but not serial: the shared lane would run it")
    if not hasattr(config, "workerinput"):
        return
    module_weight = {}
    for item in items:
        module_weight[item.module] = min(module_weight.get(item.module, 3), _weight(item))
    items.sort(key=lambda item: module_weight[item.module])  # stable: collection order within a weight
