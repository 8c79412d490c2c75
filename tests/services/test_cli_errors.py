"""A bad flag on a service's or the runner's command line: one line naming the flag and the
value, exit code 2, no traceback, nothing started."""

import pytest

from services.cli import bench as bench_cli
from services.cli import roles

SERVICE_CASES = [
    (["--run-id", "a/b*"], "run id 'a/b*': use 1-64 letters"),
    (["--run-id", "x", "--connect", "bogus"], "--connect bogus: Endpoints must be of the form"),
    (["--run-id", "x", "--cfg", "nosuch/key:1"], "--cfg nosuch/key:1: unknown key"),
    (["--run-id", "x", "--cpus", "99"], "argument --cpus: CPUs '99': this process may use CPUs"),
    (["--run-id", "x", "--listen", "tcp/1.2.3.4:99999"], "zenoh: invalid port value"),
    (["--run-id", "x", "--listen", "tcp/8.8.8.8:7447"], "zenoh: Can not create a new TCP listener bound to tcp/8.8.8.8:7447"),
]


def exit_code(call):
    try:
        return call()
    except SystemExit as exc:  # argparse's own errors
        return exc.code


@pytest.mark.zenoh
@pytest.mark.parametrize("argv,says", SERVICE_CASES, ids=[" ".join(a) for a, _ in SERVICE_CASES])
def test_a_service_refuses_a_bad_flag_in_one_line(capsys, argv, says):
    assert exit_code(lambda: roles.main("ft_sensor", argv)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and says in err[-1], err
    assert err[-1].startswith("etar-ft-sensor: error: ")
    assert not any("Traceback" in line for line in err)


@pytest.mark.parametrize("argv,says", [
    (["--connect", "bogus"], "--connect bogus: Endpoints must be of the form"),
    (["--run-id", "a/b*"], "run id 'a/b*': use 1-64 letters"),
    (["--realtime-profile", "fifo,turbo"], "unknown part 'turbo'"),
    (["--tls", "/nonexistent"], "/nonexistent/ca.pem: missing (make the run's credentials with: etar-bench certs"),
    (["--hosts", "robot"], "--hosts 'robot': no host for ft_sensor"),
    (["--hosts", "robot,ft_sensor,recorder,teacher", "--transport", "inproc"], "--hosts starts the services on hosts"),
    (["--foxglove", "70000"], "--foxglove PORT must be in 0..65535"),
    (["--foxglove", "abc"], "argument --foxglove: invalid int value: 'abc'"),
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
