"""The import rules of docs/architecture.md, read from the code: every import in services/
and in robot_sim/ points down its list of wings (lazy imports inside functions count too),
etar/ and robot_sim/ import neither services/ nor each other, kernel_plumbing/, which both
import, imports none of the three, no module imports itself back through others, and no
module, class or function is past the sizes the document sets."""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from services.runtime.roles import ROLES

ROOT = Path(__file__).resolve().parents[1]

# lowest first: a wing may import the wings before it, never one after it
WINGS = ("runtime", "scenario", "recordings", "foxglove", "ros2", "nodes", "transport", "results", "run", "cli")


# robot_sim/: each part and what of robot_sim it may import.  The wire is bytes and sockets:
# it reads the packets, the KRL channels and the RDT record, never the law, the link's
# books or the physics; the cell composes the parts the lab's KRC holds, not the wire.
SIM_PARTS = {
    "cycle": (),
    "arm": ("cycle",),
    "world": ("cycle", "arm"),
    "ati": ("cycle",),
    "krc": ("cycle", "arm"),
    "wire": ("cycle", "krc.packets", "krc.krl", "ati"),
    "cell": ("cycle", "arm", "world", "ati", "krc"),
}
SIM_TOP_MODULES = 3  # robot_sim/'s top: the cycle and the cell (and room for one more); the rest is in parts


def imports(path: Path, text: str | None = None):
    """(module imported, line) of every import in ``path``, relative ones resolved."""
    package = path.relative_to(ROOT).with_suffix("").parts[:-1]
    text = path.read_text() if text is None else text
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                module = ".".join([*base, node.module] if node.module else base)
            else:
                module = node.module
            yield module, node.lineno
            for alias in node.names:  # "from services import run" imports services.run
                yield f"{module}.{alias.name}", node.lineno


def wing_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "services" and len(parts) > 1 and parts[1] in WINGS else None


def sim_part(module: str) -> str | None:
    """The part of robot_sim/ a module belongs to ("krc.packets" for the wire's allowed
    pieces of krc/, else the folder or the top module's name)."""
    parts = module.split(".")
    if parts[0] != "robot_sim" or len(parts) < 2:
        return None
    if parts[1] == "krc" and len(parts) > 2 and parts[2] in ("packets", "krl"):
        return f"krc.{parts[2]}"
    return parts[1]


def sim_allowed(part: str, target: str) -> bool:
    if target.split(".")[0] == part.split(".")[0]:
        return True
    allowed = SIM_PARTS[part.split(".")[0]]
    return target in allowed or target.split(".")[0] in allowed


def sources(folder: str):
    return sorted((ROOT / folder).rglob("*.py"))


def test_services_has_only_wings_at_its_top():
    top = sorted(p.name for p in (ROOT / "services").iterdir() if not p.name.startswith((".", "__")))
    assert top == sorted(WINGS), "a module at the top of services/ belongs in a wing (docs/architecture.md)"
    assert [p.name for p in (ROOT / "services").glob("*.py")] == ["__init__.py"]


def test_every_wing_is_described_in_docs_architecture():
    text = (ROOT / "docs" / "architecture.md").read_text()
    for wing in WINGS:
        assert re.search(rf"`services/{wing}/`", text), f"docs/architecture.md says nothing of services/{wing}/"


@pytest.mark.parametrize("wing", WINGS)
def test_a_wing_imports_only_the_wings_below_it(wing):
    allowed = set(WINGS[:WINGS.index(wing) + 1])
    wrong = []
    for path in sources(f"services/{wing}"):
        for module, line in imports(path):
            target = wing_of(module)
            if target is not None and target not in allowed:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {module} (services/{target}/ is above "
                             f"services/{wing}/)")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("library,foreign", [("etar", ("services", "robot_sim")), ("robot_sim", ("services", "etar")),
                                             ("kernel_plumbing", ("services", "robot_sim", "etar"))])
def test_the_libraries_import_no_services_and_not_each_other(library, foreign):
    wrong = [f"{path.relative_to(ROOT)}:{line} imports {module}" for path in sources(library)
             for module, line in imports(path) if module.split(".")[0] in foreign]
    assert not wrong, "\n".join(wrong)


def test_the_rule_catches_robot_sim_importing_the_learner_and_lets_it_use_the_plumbing():
    path = ROOT / "robot_sim" / "probe.py"
    text = "from kernel_plumbing import blas\nfrom kernel_plumbing.addresses import JIT\nfrom etar import ETAR\n" \
           "import etar.inference\n"
    found = list(imports(path, text))
    assert sorted({line for m, line in found if m.split(".")[0] in ("services", "etar")}) == [3, 4]
    assert sorted({line for m, line in found if m.split(".")[0] == "kernel_plumbing"}) == [1, 2]


def test_the_rule_itself_catches_an_import_that_points_back():
    """The check reads what it should: a lazy import of the runner in a runtime module,
    and a relative import of a wing above, are both found."""
    path = ROOT / "services" / "runtime" / "probe.py"
    text = "def f():\n    from services.run.runner import Runner\n\nfrom ..cli import bench\n"
    assert sorted((line, wing_of(m)) for m, line in imports(path, text) if wing_of(m)) == [
        (2, "run"), (2, "run"), (4, "cli"), (4, "cli")]


def test_a_service_process_imports_its_own_node_only():
    """What each role's program has loaded once its command line is built (what --help
    loads; its node's own start-up is not covered): its node's module and none of the other
    roles' (their imports cost every process of a run a second or more: services.nodes),
    MuJoCo only in the robot, the cell's compiled kernels only in the robot and the sensor
    (a reader of the Net F/T's wire needs robot_sim.ati.rdt, not the sensor model), and no
    numba at all in the roles that compile nothing (its import and the kernels it loads were
    a second of every such process's start): nor in an in-process run's MCAP writer helper."""
    probe = ("import json, sys\nfrom services.cli.roles import build_parser\nbuild_parser(sys.argv[1])\n"
             "print(json.dumps({'nodes': [m for m in sys.modules if m.startswith('services.nodes.')],"
             " 'mujoco': 'mujoco' in sys.modules, 'numba': 'numba' in sys.modules,"
             " 'kernels': any(m in sys.modules for m in ('robot_sim.world.physics', 'robot_sim.krc.law', 'robot_sim.ati.sensor'))}))\n")
    roles = tuple(ROLES)
    # one process per role, all at once: the test's cost is one start-up, not seven
    probes = {role: subprocess.Popen([sys.executable, "-c", probe, role], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True) for role in roles}
    # what the helper imports: its module, and the recorder's opener it is sent (VisualRecordings)
    helper = subprocess.Popen([sys.executable, "-c", "import sys, services.recordings.offload, services.foxglove.tap; "
                               "print('numba' in sys.modules)"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    for role, proc in probes.items():
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr[-2000:]
        loaded = json.loads(stdout)
        others = [f"services.nodes.{r}" for r in roles if r != role and f"services.nodes.{r}" in loaded["nodes"]]
        assert not others, f"the {role} program imports other roles' nodes: {others}"
        assert f"services.nodes.{role}" in loaded["nodes"], loaded
        assert loaded["mujoco"] == (role == "robot"), f"{role}: MuJoCo loaded: {loaded['mujoco']}"
        assert loaded["kernels"] == (role in ("robot", "ft_sensor")), f"{role}: the cell's kernels loaded: {loaded}"
        if role in ("recorder", "foxglove_bridge", "ros2"):
            assert not loaded["numba"], f"the {role} program imports numba"
    assert helper.communicate(timeout=120)[0].strip() == "False", "the MCAP writer helper imports numba"


def test_robot_sim_is_in_parts_with_few_modules_at_its_top():
    top = sorted(p.stem for p in (ROOT / "robot_sim").glob("*.py") if p.name != "__init__.py")
    folders = sorted(p.name for p in (ROOT / "robot_sim").iterdir() if p.is_dir() and not p.name.startswith(("_", ".")))
    assert len(top) <= SIM_TOP_MODULES, f"robot_sim/ has {len(top)} modules at its top: {top}"
    assert set(top) | set(folders) == set(SIM_PARTS), (top, folders)
    text = (ROOT / "docs" / "architecture.md").read_text()
    for part in folders:
        assert f"`robot_sim/{part}/`" in text, f"docs/architecture.md says nothing of robot_sim/{part}/"


def sim_wrong(path: Path, text: str | None = None) -> list[str]:
    rel = path.relative_to(ROOT / "robot_sim")
    part = rel.parts[0] if len(rel.parts) > 1 else rel.stem
    if part == "__init__.py":
        return []
    return [f"{path.relative_to(ROOT)}:{line} imports {module} (robot_sim/{part} may import "
            f"{', '.join(SIM_PARTS[part]) or 'nothing'} of robot_sim)"
            for module, line in imports(path, text)
            if (target := sim_part(module)) is not None and not sim_allowed(part, target)]


def test_each_part_of_robot_sim_imports_only_what_its_rule_allows():
    wrong = [w for path in sources("robot_sim") for w in sim_wrong(path)]
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("where,text,bad", [
    ("wire/probe.py", "from robot_sim.krc.law import KrcController\n", True),
    ("wire/probe.py", "from robot_sim.world import physics\n", True),
    ("wire/probe.py", "def f():\n    from robot_sim.cell import RobotCell\n", True),
    ("wire/probe.py", "from robot_sim.krc.packets import CommandPacket\nfrom robot_sim.ati.rdt import RdtRecord\n", False),
    ("cycle.py", "from robot_sim.arm.description import LWR4\n", True),
    ("ati/probe.py", "from robot_sim.krc.packets import FriState\n", True),
    ("world/probe.py", "from robot_sim.krc.link import FriLink\n", True),
    ("cell.py", "from robot_sim.wire.fri_udp import FriUdpEndpoint\n", True),
    ("krc/probe.py", "from robot_sim.arm.kinematics import ArmKinematics\nfrom . import link\n", False),
])
def test_the_robot_sim_rule_catches_a_probe_that_breaks_it(where, text, bad):
    assert bool(sim_wrong(ROOT / "robot_sim" / where, text)) == bad


def import_graph() -> dict[str, set[str]]:
    """Every product module and the product modules it imports (lazy imports count)."""
    modules = {}
    for package in ("etar", "robot_sim", "kernel_plumbing", "services"):
        for path in sources(package):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            modules[name.removesuffix(".__init__")] = path
    graph = {}
    for name, path in modules.items():
        graph[name] = {m for m, _ in imports(path) if m in modules and m != name}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan), each a circle."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_module_imports_itself_back_through_others():
    """A package's __init__ that re-exports lazily is the one pattern allowed to point at
    its own children (``services/__init__``'s run_scenario)."""
    graph = import_graph()
    for name in graph:
        graph[name] = {m for m in graph[name] if not (name.count(".") == 0 and m.startswith(name + "."))}
    assert circles(graph) == []


def test_the_circle_check_finds_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_zenoh_port_has_one_home_that_compose_follows():
    """The Zenoh port is services.transport.session.ZENOH_PORT; docker-compose.yml cannot
    import it, so its default is checked against it here."""
    import re

    from services.transport.session import ZENOH_PORT

    compose = (ROOT / "docker-compose.yml").read_text()
    defaults = set(re.findall(r"\$\{ZENOH_PORT:-(\d+)\}", compose))
    assert defaults == {str(ZENOH_PORT)}, defaults
    product = [p for p in (ROOT / "services").rglob("*.py") if "7447" in p.read_text()
               and p.name not in ("session.py",) and "7447" in "".join(
                   line for line in p.read_text().splitlines() if not line.lstrip().startswith(("#", "etar-bench")))]
    assert product == [], f"the Zenoh port written out beside its home: {product}"


# docs/architecture.md "Sizes": past these a piece is doing more than one thing
MAX_MODULE_LINES, MAX_CLASS_LINES, MAX_FUNCTION_LINES = 600, 300, 100
# an argparse table, a list of flags read top to bottom, named in docs/architecture.md
SIZE_EXCEPTIONS = {"services/cli/bench.py:build_parser"}


def oversized(path: Path, text: str | None = None) -> list[str]:
    """The module, classes and functions in ``path`` past the sizes, as 'path[:name] N lines'."""
    text = path.read_text() if text is None else text
    where = path.relative_to(ROOT).as_posix()
    found = []
    lines = len(text.splitlines())
    if lines > MAX_MODULE_LINES:
        found.append(f"{where} {lines} lines")
    for node in ast.walk(ast.parse(text, str(path))):
        limit = (MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else
                 MAX_FUNCTION_LINES if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) else None)
        if limit is None:
            continue
        size = node.end_lineno - node.lineno + 1
        if size > limit and f"{where}:{node.name}" not in SIZE_EXCEPTIONS:
            found.append(f"{where}:{node.name} {size} lines")
    return found


def test_no_product_module_class_or_function_is_past_its_size():
    found = [f for folder in ("etar", "robot_sim", "services", "kernel_plumbing") for path in sources(folder)
             for f in oversized(path)]
    assert found == [], "past the sizes of docs/architecture.md 'Sizes':\n" + "\n".join(found)


def test_the_size_rule_catches_each_kind_and_names_its_exception_in_the_docs():
    probe = ROOT / "services" / "run" / "probe.py"
    long_function = "def f():\n" + "    x = 1\n" * MAX_FUNCTION_LINES
    long_class = "class C:\n" + "    x = 1\n" * MAX_CLASS_LINES
    assert oversized(probe, long_function) == ["services/run/probe.py:f 101 lines"]
    assert oversized(probe, long_class) == ["services/run/probe.py:C 301 lines"]
    assert oversized(probe, "x = 1\n" * (MAX_MODULE_LINES + 1)) == ["services/run/probe.py 601 lines"]
    assert oversized(probe, "x = 1\n" * MAX_MODULE_LINES) == []
    sizes = (ROOT / "docs" / "architecture.md").read_text().split("## Sizes", 1)[1].split("\n## ", 1)[0]
    for exception in SIZE_EXCEPTIONS:
        path, name = exception.split(":")
        assert f"`{path}`" in sizes and f"`{name}`" in sizes, exception


def topic_literals(path: Path, text: str | None = None) -> list[str]:
    """Every string in ``path`` that is a message's topic (``robot/state``) or its recorded
    channel (``/robot/state``), docstrings aside, as 'path:line 'topic''."""
    from services.runtime.messages import MESSAGES

    topics = {m.topic for m in MESSAGES.values()} | {m.channel for m in MESSAGES.values()}
    tree = ast.parse(path.read_text() if text is None else text, str(path))
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr)}
    where = path.relative_to(ROOT).as_posix()
    return [f"{where}:{node.lineno} {node.value!r}" for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and node.value in topics and id(node) not in docstrings]


def test_topics_are_named_only_through_their_message_types():
    """A topic is written once, in services/runtime/messages.py; everywhere else it is
    ``ROBOT_STATE.topic`` (on the bus) or ``ROBOT_STATE.channel`` (in a recording)."""
    registry = ROOT / "services" / "runtime" / "messages.py"
    found = [f for folder in ("etar", "robot_sim", "services", "kernel_plumbing", "bench") for path in sources(folder)
             if path != registry for f in topic_literals(path)]
    assert found == [], "topic names written out of their message types:\n" + "\n".join(found)


def test_the_topic_rule_catches_a_literal_and_leaves_prose_alone():
    probe = ROOT / "services" / "nodes" / "probe.py"
    assert topic_literals(probe, 'x = "robot/state"\n') == ["services/nodes/probe.py:1 'robot/state'"]
    assert topic_literals(probe, 'if topic == "/ft/wrench":\n    pass\n') == ["services/nodes/probe.py:1 '/ft/wrench'"]
    assert topic_literals(probe, '"""Reads robot/state."""\nx = "robot/state and more"\n') == []
    assert topic_literals(probe, "from services.runtime.messages import ROBOT_STATE\nx = ROBOT_STATE.topic\n") == []


def test_the_services_tests_are_in_the_wings_they_test():
    top = ROOT / "tests" / "services"
    assert sorted(p.name for p in top.glob("test_*.py")) == [], "a test at tests/services/'s top: move it to its wing"
    folders = {p.name for p in top.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders <= set(WINGS), folders - set(WINGS)
