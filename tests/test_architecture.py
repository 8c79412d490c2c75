"""The import rules of docs/architecture.md, read from the code: every import in services/
points down the list of wings (lazy imports inside functions count too), etar/ and
robot_sim/ import neither services/ nor each other, and kernel_plumbing/, which both
import, imports none of the three."""

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
WINGS = ("runtime", "scenario", "recordings", "foxglove", "nodes", "transport", "results", "run", "cli")


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
    (a reader of the Net F/T's wire needs robot_sim.rdt, not the sensor model)."""
    probe = ("import json, sys\nfrom services.cli.roles import build_parser\nbuild_parser(sys.argv[1])\n"
             "print(json.dumps({'nodes': [m for m in sys.modules if m.startswith('services.nodes.')],"
             " 'mujoco': 'mujoco' in sys.modules,"
             " 'kernels': any(m in sys.modules for m in ('robot_sim.physics', 'robot_sim.krc', 'robot_sim.ati'))}))\n")
    roles = tuple(ROLES)
    # one process per role, all at once: the test's cost is one start-up, not seven
    probes = {role: subprocess.Popen([sys.executable, "-c", probe, role], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True) for role in roles}
    for role, proc in probes.items():
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr[-2000:]
        loaded = json.loads(stdout)
        others = [f"services.nodes.{r}" for r in roles if r != role and f"services.nodes.{r}" in loaded["nodes"]]
        assert not others, f"the {role} program imports other roles' nodes: {others}"
        assert f"services.nodes.{role}" in loaded["nodes"], loaded
        assert loaded["mujoco"] == (role == "robot"), f"{role}: MuJoCo loaded: {loaded['mujoco']}"
        assert loaded["kernels"] == (role in ("robot", "ft_sensor")), f"{role}: the cell's kernels loaded: {loaded}"


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
