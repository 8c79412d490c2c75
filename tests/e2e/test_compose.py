"""docker-compose.yml: every service runs a real CLI of this project with valid flags
(fast), and the smoke scenario comes up with docker-compose on podman (slow)."""

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import yaml

from services.cli import bench as bench_cli
from services.cli import roles
from services.runtime.roles import ROLES as ALL_ROLES

ROOT = Path(__file__).resolve().parents[2]
PARSERS = {"etar-bench": bench_cli.build_parser,
           **{r.program: (lambda name=name: roles.build_parser(name)) for name, r in ALL_ROLES.items()}}
# every role of a run but the live view's bridge and the ROS 2 node: the runner attaches to
# compose's services, and --attach refuses --foxglove and --ros2
ROLES = set(ALL_ROLES) - {"foxglove_bridge", "ros2"}


def expand(text: str) -> str:
    """docker-compose's ${VAR:-default} with the defaults."""
    return re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: os.environ.get(m.group(1), m.group(2)), text)


def compose():
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def test_every_compose_command_is_a_real_cli_with_valid_flags():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    services = compose()["services"]
    assert ROLES | {"router", "runner"} <= set(services)
    run_ids = set()
    for name, svc in services.items():
        argv = shlex.split(expand(svc["command"]))
        exe, args = argv[0], argv[1:]
        assert exe in scripts, f"{name}: {exe} is not a console script of this project"
        assert exe in PARSERS, f"{name}: no parser known for {exe}"
        try:
            parsed = PARSERS[exe]().parse_args(args)
        except SystemExit as exc:
            pytest.fail(f"{name}: `{' '.join(argv)}` has invalid flags (argparse exit {exc.code})")
        if hasattr(parsed, "run_id") and parsed.run_id:
            run_ids.add(parsed.run_id)
        if name in ROLES | {"runner"}:
            assert parsed.mode == "client" and parsed.connect, f"{name} must join the router"
    assert len(run_ids) == 1, f"every role must use the same run id, got {run_ids}"
    # the runner drives what compose started rather than spawning its own
    runner = bench_cli.build_parser().parse_args(shlex.split(expand(services["runner"]["command"]))[1:])
    assert runner.attach and runner.command == "run"


def _podman_ready() -> tuple[bool, str]:
    if os.geteuid() != 0:
        return False, "needs root (apt-get, podman)"
    if not shutil.which("apt-get") and not shutil.which("podman"):
        return False, "no apt-get and no podman on this machine"
    return True, ""


@pytest.mark.compose
@pytest.mark.slow
@pytest.mark.zenoh
def test_smoke_scenario_on_docker_compose_with_podman(tmp_path):
    ok, why = _podman_ready()
    if not ok:
        pytest.skip(why)
    already = _podman_service_pids()
    try:
        _smoke_on_compose(tmp_path)
    finally:
        # the machine as it was: the service setup-podman.sh started would otherwise take
        # CPU from every test after this one (the realtime ones notice)
        for pid in _podman_service_pids() - already:
            os.kill(pid, signal.SIGTERM)


def _podman_service_pids() -> set[int]:
    found = subprocess.run(["pgrep", "-f", "podman system service"], capture_output=True, text=True)
    return {int(p) for p in found.stdout.split()}


def _smoke_on_compose(tmp_path):
    t0 = time.monotonic()
    setup = subprocess.run(["bash", str(ROOT / "docker" / "setup-podman.sh")], capture_output=True, text=True,
                           timeout=1500)
    print(setup.stdout[-2000:], setup.stderr[-2000:])
    assert setup.returncode == 0, "docker/setup-podman.sh failed"
    print(f"setup: {time.monotonic() - t0:.1f} s")
    run_id = f"compose{int(time.time())}"
    env = dict(os.environ, DOCKER_HOST="unix:///tmp/etar-podman.sock", RUN_ID=run_id,
               ZENOH_PORT=str(_free_port()), COMPOSE_PROJECT_NAME=run_id)
    runs = ROOT / "runs"
    cmd = ["docker-compose", "-f", str(ROOT / "docker-compose.yml"), "up", "--build", "--exit-code-from", "runner"]
    t1 = time.monotonic()
    up = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1500)
    print(up.stdout[-6000:], up.stderr[-3000:])
    runner_code = up.returncode
    if up.returncode and LOG_PRINTER_CRASH in up.stderr:
        # docker-compose 1.29's own crash: a container 'start' event it could not inspect (podman's API,
        # busy with a rebuild) handed its log printer None (compose/project.py, build_container_event),
        # and compose exited 1 whatever the containers did.  The runner container's own exit code says
        runner_code = _exit_code(f"{run_id}_runner_1", env)
        print(f"docker-compose crashed in its log printer; the runner container exited with {runner_code}")
    subprocess.run(["docker-compose", "-f", str(ROOT / "docker-compose.yml"), "down"], cwd=ROOT, env=env,
                   capture_output=True, timeout=300)
    print(f"compose up: {time.monotonic() - t1:.1f} s")
    assert runner_code == 0, "the runner container failed"
    # the image's wheel carries the compiled extension (setup.py may take the in-place build's),
    # and it loads there: robot_sim would otherwise fall back to Pinocchio's bindings unseen
    native = subprocess.run(["podman", "run", "--rm", "localhost/etar-testbench:latest", "python", "-c",
                             "import robot_sim.arm._pinocchio_inplace"], capture_output=True, text=True, timeout=120)
    assert native.returncode == 0, native.stderr[-2000:]
    out = runs / run_id
    report = json.loads((out / "report.json").read_text())
    assert report["error"] is None
    from services.recordings.reader import read_episode

    files = sorted((out / "recordings").glob("*.mcap"))
    assert [f.name for f in files] == ["demonstration_00.mcap", "demonstration_01.mcap", "reproduction_00.mcap"]
    for f in files:
        ep = read_episode(f)
        assert ep.complete and {"/robot/state", "/ft/wrench", "/robot/contact"} <= set(ep.topics())
    shutil.rmtree(out, ignore_errors=True)


LOG_PRINTER_CRASH = "AttributeError: 'NoneType' object has no attribute 'log_stream'"


def _exit_code(container: str, env: dict) -> int | None:
    got = subprocess.run(["podman", "inspect", "--format", "{{.State.ExitCode}}", container], env=env,
                         capture_output=True, text=True, timeout=60)
    return int(got.stdout.strip()) if got.returncode == 0 and got.stdout.strip().lstrip("-").isdigit() else None


def _free_port() -> int:
    from services.transport.launch import free_port

    return free_port()


@pytest.mark.slow
@pytest.mark.zenoh
def test_compose_ending_the_runner_with_its_services_is_a_clean_exit(tmp_path):
    """The compose file's commands as processes on this host, ended as ``docker-compose up
    --exit-code-from runner`` ends them: once the runner has written its report it shuts the
    services down, the first of them to exit makes compose stop every container left, the
    runner's with SIGTERM.  That SIGTERM ends a run that is whole: exit 0, not an interrupt
    (before, compose said "the runner container failed" once in 14 runs here)."""
    run_id = f"attach{os.getpid()}"
    from tests import support

    # the scenario cut short: what is looked at is how the run ends (lockstep, as compose's services)
    held = tmp_path / "hold.yaml"
    held.write_text(support.hold(1.0, {"clock": "lockstep"}).to_yaml())
    env = dict(os.environ, RUN_ID=run_id, ZENOH_PORT=str(_free_port()), SCENARIO=str(held))
    bin_dir = Path(sys.executable).parent
    argvs = {}
    for name, svc in compose()["services"].items():
        text = re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: env.get(m.group(1)) or m.group(2), svc["command"])
        argv = [a.replace("/runs/", f"{tmp_path}/") for a in shlex.split(text)]
        argvs[name] = [str(bin_dir / argv[0]), *argv[1:]]
    procs, logs = {}, {}
    try:
        for name in ["router", *sorted(ROLES), "runner"]:  # depends_on's order
            logs[name] = open(tmp_path / f"{name}.log", "w")
            procs[name] = subprocess.Popen(argvs[name], cwd=ROOT, env=env, stdout=logs[name],
                                           stderr=subprocess.STDOUT)
        services = [p for name, p in procs.items() if name != "runner"]
        deadline = time.monotonic() + 300
        while procs["runner"].poll() is None and all(p.poll() is None for p in services):
            assert time.monotonic() < deadline, "the run did not end in 300 s"
            time.sleep(0.005)
        for p in procs.values():  # compose's abort: every container left is stopped
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        code = procs["runner"].wait(timeout=60)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()
    said = (tmp_path / "runner.log").read_text()
    assert code == 0, said[-3000:]
    assert json.loads((tmp_path / run_id / "report.json").read_text())["error"] is None
    assert "SIGTERM" not in said
