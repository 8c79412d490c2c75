"""A bad flag on a service's or the runner's command line: one line naming the flag and the
value, exit code 2, no traceback, nothing started."""

import pytest

from services.cli import bench as bench_cli
from services.cli import roles

# (role, flags, what the one line says after "<program>: error: ")
SERVICE_CASES = [
    ("ft_sensor", ["--run-id", "a/b*"], "--run-id a/b*: use 1-64 letters"),
    ("ft_sensor", [], "--run-id: required"),
    ("ft_sensor", ["--run-id", "x", "--clock", "fast"], "--clock fast: not one of lockstep, realtime"),
    ("ft_sensor", ["--run-id", "x", "--seed", "abc"], "--seed abc: expected an integer"),
    ("ft_sensor", ["--run-id", "x", "--noise-scale", "-1"], "--noise-scale -1: must be a finite number >= 0"),
    ("ft_sensor", ["--run-id", "x", "--bogus"], "--bogus: not a flag of this program"),
    ("ft_sensor", ["--run-id", "x", "--cfg", "nosuch/key:1"], "--cfg nosuch/key:1: unknown key"),
    ("ft_sensor", ["--run-id", "x", "--cfg", "nocolon"], "--cfg nocolon: expected KEY:VALUE"),
    # JSON5's error was drawn over lines, escaped into the one line as \n sequences
    ("ft_sensor", ["--run-id", "x", "--cfg", "a:{bad json"],
     "--cfg a:{bad json: expected array, boolean, null, number, object, or string (at line:column 1:1 of the value)"),
    ("ft_sensor", ["--run-id", "x", "--cpus", "99"], "--cpus 99: this process may use CPUs"),
    ("ft_sensor", ["--run-id", "x", "--cpus", "a-b"], "--cpus a-b: expected CPUs like 1 or 0,2-3"),
    ("robot", ["--run-id", "x", "--sched-fifo", "1000"], "--sched-fifo 1000: a SCHED_FIFO priority is 1..99 (0: off)"),
    ("robot", ["--run-id", "x", "--sched-fifo", "-5"], "--sched-fifo -5: a SCHED_FIFO priority is 1..99 (0: off)"),
    ("robot", ["--run-id", "x", "--sched-fifo", "high"], "--sched-fifo high: expected a priority, an integer in 1..99"),
    ("robot", ["--run-id", "x", "--connect", "tcp/127.0.0.1:99999"],
     "--connect tcp/127.0.0.1:99999: port '99999' is not in 1..65535"),
    ("robot", ["--run-id", "x", "--connect", "tcp/127.0.0.1:0"],
     "--connect tcp/127.0.0.1:0: port '0' is not in 1..65535"),
    ("robot", ["--run-id", "x", "--connect", "tcp/127.0.0.1"], "--connect tcp/127.0.0.1: expected tcp/HOST:PORT"),
    ("robot", ["--run-id", "x", "--connect", "tcp/::1:7447"], "--connect tcp/::1:7447: '::1' is not a host name"),
    ("robot", ["--run-id", "x", "--connect", "foo/1.2.3.4:7"], "--connect foo/1.2.3.4:7: unknown protocol 'foo'"),
    ("robot", ["--run-id", "x", "--connect", "bogus"], "--connect bogus: Endpoints must be of the form"),
    ("robot", ["--run-id", "x", "--fri-packet-loss", "2"], "--fri-packet-loss 2: expected a probability in [0, 1]"),
    ("robot", ["--run-id", "x", "--answer-timeout", "0"], "--answer-timeout 0: must be a finite number of seconds > 0"),
    ("ft_sensor", ["--run-id", "x", "--listen", "garbage"], "--listen garbage: Endpoints must be of the form"),
    ("ft_sensor", ["--run-id", "x", "--listen", "tcp/1.2.3.4:99999"],
     "--listen tcp/1.2.3.4:99999: port '99999' is not in 0..65535 (0: any free port)"),
    ("recorder", ["--run-id", "x", "--visual-rate-hz", "-1"], "--visual-rate-hz -1: must be 0 (none) or in (0, 1000]"),
    ("foxglove_bridge", ["--run-id", "x", "--visual-rate-hz", "0"], "--visual-rate-hz 0: must be in (0, 1000]"),
    ("foxglove_bridge", ["--run-id", "x", "--port", "70000"], "--port 70000: must be in 0..65535"),
    ("phase_estimator", ["--run-id", "x", "--model", "/nonexistent/model.json"],
     "--model /nonexistent/model.json: no such file"),
    ("impedance_commander", ["--run-id", "x", "--lead", "0"], "--lead 0: must be > 0 m"),
]


def exit_code(call):
    try:
        return call()
    except SystemExit as exc:  # argparse's own errors
        return exc.code


def refused_in_one_line(capsys, role, argv, says):
    """``role``'s program with ``argv``: exit code 2, one line on stderr naming the flag and
    the value, no traceback, nothing started (no "ready" line)."""
    program = roles.ROLES[role].program
    assert exit_code(lambda: roles.main(role, argv)) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"{program}: error: ") and says in lines[0], lines
    assert "Traceback" not in err and "ready" not in err + out, (out, err)
    return lines[0]


@pytest.mark.zenoh
@pytest.mark.parametrize("role,argv,says", SERVICE_CASES, ids=[f"{r} {' '.join(a)}" for r, a, _ in SERVICE_CASES])
def test_a_service_refuses_a_bad_flag_in_one_line(capsys, role, argv, says):
    refused_in_one_line(capsys, role, argv, says)


@pytest.mark.zenoh
def test_a_service_names_the_endpoint_it_cannot_listen_on(capsys):
    """A valid endpoint whose address is not this machine's: Zenoh's own words, after the flag."""
    argv = ["--run-id", "x", "--listen", "tcp/8.8.8.8:7447"]
    refused_in_one_line(capsys, "ft_sensor", argv,
                        "--listen tcp/8.8.8.8:7447: Can not create a new TCP listener bound to tcp/8.8.8.8:7447")


@pytest.mark.zenoh
@pytest.mark.parametrize("where,says", [
    ("file", "not a folder (it is a file)"),
    ("file/sub", "cannot be made: {file} is a file, not a folder"),
    ("file/sub/deeper", "cannot be made: {file} is a file, not a folder"),
])
def test_the_recorder_refuses_an_out_dir_it_cannot_write_in(capsys, tmp_path, where, says):
    file = tmp_path / "file"
    file.write_text("not a folder\n")
    out_dir = tmp_path / where
    line = refused_in_one_line(capsys, "recorder", ["--run-id", "x", "--out-dir", str(out_dir)],
                               f"--out-dir {out_dir}: " + says.format(file=file))
    assert line == f"etar-recorder: error: --out-dir {out_dir}: " + says.format(file=file)


def test_the_recorder_refuses_a_folder_it_may_not_write_in(tmp_path, monkeypatch):
    """(root may write anywhere: the permission is the system's answer, asked through os.access)"""
    import os

    from services.nodes.recorder import RecorderConfig
    from services.runtime.config import FieldError

    monkeypatch.setattr(os, "access", lambda path, mode: False)
    with pytest.raises(FieldError, match="may not write in"):
        RecorderConfig(out_dir=str(tmp_path))
    with pytest.raises(FieldError, match=f"cannot be made: this user may not write in {tmp_path}"):
        RecorderConfig(out_dir=str(tmp_path / "new"))


def test_the_recorder_takes_a_folder_still_to_be_made(tmp_path):
    from services.nodes.recorder import RecorderConfig

    RecorderConfig(out_dir=str(tmp_path / "run" / "recordings"))  # made when the first episode begins
    assert not (tmp_path / "run").exists()


@pytest.mark.zenoh
@pytest.mark.parametrize("role,argv,says", [
    ("robot", ["--run-id", "x", "--sched-fifo", "1000"], "--sched-fifo 1000: a SCHED_FIFO priority is 1..99"),
    ("robot", ["--run-id", "x", "--connect", "tcp/127.0.0.1:99999"], "--connect tcp/127.0.0.1:99999: port '99999' is not in 1..65535"),
    ("recorder", ["--run-id", "x", "--out-dir", "{file}"], "--out-dir {file}: not a folder"),
])
def test_the_program_itself_refuses_before_it_starts(tmp_path, role, argv, says):
    """The real entry point in a process of its own: stderr is exactly one line (no Zenoh
    log, no ready line, no usage), stdout nothing, exit code 2."""
    import subprocess
    import sys

    file = tmp_path / "a-file"
    file.write_text("")
    argv = [a.format(file=file) for a in argv]
    done = subprocess.run([sys.executable, "-m", "services.cli.roles", role, *argv], capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 2, done
    assert done.stdout == ""
    assert done.stderr.splitlines() == [done.stderr.strip()], done.stderr
    assert done.stderr.startswith(f"{roles.ROLES[role].program}: error: {says.format(file=file)}"), done.stderr


def test_a_priority_not_granted_says_why(monkeypatch):
    """The ready line names a SCHED_FIFO priority that was refused, and the system's reason."""
    import os

    from services.transport import process

    def refuse(pid, policy, param):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    reason = process.fifo_refusal(50)
    assert reason == "Operation not permitted"
    assert process.fifo_words(50, False, reason) == "SCHED_FIFO 50 not granted: Operation not permitted"
    assert process.fifo_words(0, False, None) == "SCHED_FIFO off"
    assert process.fifo_words(60, 60, None) == "SCHED_FIFO 60"
    with pytest.raises(ValueError, match=r"--sched-fifo 100: a SCHED_FIFO priority is 1\.\.99"):
        process.ProcessConfig(run_id="x", zenoh=None, sched_fifo=100)


@pytest.mark.parametrize("endpoint,listen", [
    ("tcp/127.0.0.1:7447", False), ("tcp/localhost:7447", False), ("tcp/[::1]:7447", False),
    ("tcp/10.0.0.1:7447?iface=eth0#rx_buffer_size=65536", False), ("tls/router:7447", False),
    ("udp/127.0.0.1:65535", False), ("unixsock-stream//tmp/etar.sock", False), ("tcp/127.0.0.1:0", True),
    ("tcp/0.0.0.0:7447", True),
])
def test_an_endpoint_that_can_work_is_taken(endpoint, listen):
    from services.transport.session import check_endpoint

    assert check_endpoint(endpoint, "--listen" if listen else "--connect", listen=listen) == endpoint


@pytest.mark.parametrize("listen", ["garbage", "tcp/127.0.0.1:99999", "tcp/127.0.0.1:-1", "tcp/:7447", "quack/x:1"])
def test_a_router_refuses_the_endpoint_a_service_refuses(listen):
    """The validation lives in ZenohOptions.config (check_endpoint), so a router that makes
    its options itself (etar-bench router) refuses the same endpoints, naming the flag."""
    from services.transport.session import EndpointError, ZenohOptions

    with pytest.raises(EndpointError) as caught:
        ZenohOptions(mode="router", connect=(), listen=(listen,)).config()
    assert str(caught.value).startswith(f"--listen {listen}: ")
    assert (caught.value.flag, caught.value.endpoint) == ("--listen", listen)
    assert isinstance(caught.value, ValueError)


@pytest.mark.parametrize("argv,says", [
    (["--connect", "bogus"], "--connect bogus: Endpoints must be of the form"),
    (["--run-id", "a/b*"], "run id 'a/b*': use 1-64 letters"),
    (["--realtime-profile", "fifo,turbo"], "unknown part 'turbo'"),
    (["--tls", "/nonexistent"], "/nonexistent/ca.pem: missing (make the run's credentials with: etar-bench certs"),
    (["--hosts", "robot"], "--hosts 'robot': no host for ft_sensor"),
    (["--hosts", "robot,ft_sensor,recorder,teacher", "--transport", "inproc"], "--hosts starts the services on hosts"),
    (["--foxglove", "70000"], "--foxglove PORT must be in 0..65535"),
    (["--foxglove", "abc"], "--foxglove abc: expected an integer"),
    (["--foxglove", "--tls", "/nonexistent"], "--foxglove cannot be combined with --tls, --hosts or --attach"),
])
def test_the_runner_refuses_a_bad_flag_before_it_starts_anything(capsys, tmp_path, argv, says):
    out = tmp_path / "run"
    assert exit_code(lambda: bench_cli.main(["run", "scenarios/smoke.yaml", "--out", str(out), *argv])) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert says in err[-1] and err[-1].startswith("etar-bench run: error: "), err
    assert not any("Traceback" in line for line in err)
    assert not out.exists()  # nothing was started, nothing written


def test_the_runner_refuses_a_live_view_port_that_is_taken(capsys, tmp_path):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = tmp_path / "run"
        assert bench_cli.main(["run", "scenarios/smoke.yaml", "--out", str(out), "--foxglove", str(port)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"etar-bench run: error: --foxglove {port}: 127.0.0.1:{port} is taken (Address already in use); "
                   "choose another port, or 0 for any free one"]
    assert not out.exists()


@pytest.mark.parametrize("content", [b'{"a":', b"\xff\xfe garbage", b""])
def test_report_json_on_a_corrupt_report_names_the_file(capsys, tmp_path, content):
    (tmp_path / "report.txt").write_text("a report\n")
    (tmp_path / "report.json").write_bytes(content)
    assert bench_cli.main(["report", str(tmp_path), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"etar-bench report: {tmp_path / 'report.json'}: not a JSON report")


@pytest.mark.parametrize("argv", [["etar-bench", "check", "scenarios/smoke.yaml"],
                                  ["etar", "inspect", "scenarios/models/valley.json"]], ids=["etar-bench", "etar"])
def test_output_whose_reader_is_gone_ends_quietly(argv):
    """`| head` closes the pipe before the program is done: no traceback, no error line, exit 141
    (what a program SIGPIPE ends exits with), whatever is left unsaid."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    program = Path(sys.executable).parent / argv[0]
    proc = subprocess.Popen([str(program), *argv[1:]], cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader gone before the first line
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 141, (proc.returncode, err.decode())
    assert err == b"", err.decode()


def test_the_live_views_bridge_on_a_host_it_cannot_listen_on_names_no_flag_of_another_command(capsys):
    """The node's own program has --host and --port, not etar-bench run's --foxglove."""
    assert exit_code(lambda: roles.main("foxglove_bridge", ["--run-id", "x", "--host", "not a host"])) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("etar-foxglove-bridge: error: the live view cannot listen on not a host:"), err
    assert "--foxglove" not in err[-1] and not any("Traceback" in line for line in err)
