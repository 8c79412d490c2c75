"""Who may talk to a run: with its credentials (etar-bench certs, --tls) the runner is the
run's Zenoh router, mutual TLS only, and only the run's roles may use its keys.  Foreign
sessions try to join a live run: without TLS, with another CA's certificate, and with a
certificate of the run's own CA under another name.  None of them gets a message in or out."""

import threading
import time

import pytest
import zenoh

from services.recordings.reader import read_episode
from services.runtime import topics
from services.transport.credentials import CredentialsError, client_options, make_credentials
from services.transport.session import ZenohOptions, open_session
from tests import support

# a whole run (or the service processes) over Zenoh: the slow lane
pytestmark = [pytest.mark.slow, pytest.mark.zenoh]


def test_only_the_runs_credentials_get_a_message_into_or_out_of_it(tmp_path):
    creds = make_credentials(tmp_path / "run", roles=("runner", "robot", "ft_sensor", "teacher", "phase_estimator",
                                                      "impedance_commander", "recorder", "intruder"))
    evil = make_credentials(tmp_path / "evil", roles=("robot",))
    run_id = f"tls-{int(time.time() * 1000)}"
    runner = support.runner(support.hold(4, {"clock": "lockstep"}), tmp_path / "out", run_id=run_id, tls=str(creds))
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("report", runner.run()), daemon=True)
    thread.start()
    assert runner.ready.wait(60), "the services were not up after 60 s"
    endpoint = runner.cell.endpoint
    assert endpoint.startswith("tls/127.0.0.1:")

    # no TLS at all, and a certificate another CA signed: refused at the handshake
    for what, options in (("plain tcp", ZenohOptions(mode="client", connect=(endpoint.replace("tls/", "tcp/"),),
                                                     listen=())),
                          ("another CA", client_options(evil, "robot", endpoint))):
        with pytest.raises(zenoh.ZError):
            open_session(options).close()
            pytest.fail(f"{what}: the run's router accepted the session")

    # the run's CA, another name: a session, but the router's access control drops its traffic
    intruder = open_session(client_options(creds, "intruder", endpoint))
    seen = []
    intruder.declare_subscriber(topics.key(run_id, "**"), lambda s: seen.append(str(s.key_expr)))
    forged = b'{"seq": 1, "forged": true}'
    sent = 0
    try:
        while thread.is_alive() and sent < 200:
            for topic in ("robot/state", "robot/command", "estimator/phase", "robot/episode"):
                intruder.put(topics.key(run_id, topic), forged)
            sent += 1
            time.sleep(0.01)
        replies = list(intruder.get(topics.control(run_id, "robot"), payload=b'{"cmd": "status"}', timeout=2.0))
    finally:
        intruder.close()
    thread.join(120)
    assert not thread.is_alive(), "the run did not end"
    report = result["report"]
    assert sent >= 50, "the run ended before the intruder had tried"
    assert report["error"] is None, report["error"]
    (rp,) = report["reproductions"]
    print(f"reproduction over TLS: {rp['reason']}, reached goal {rp['reached_goal']}, hold {rp['hold']}")
    assert rp["reason"] == "elapsed" and rp["hold"] is None and rp["undecodable_messages"] == 0, rp["reason"]
    assert not [k for k in seen if not k.endswith(("robot/state", "robot/command", "estimator/phase",
                                                   "robot/episode"))], seen[:5]
    assert len(seen) == 4 * sent  # only its own puts, which Zenoh hands to the session's own subscriber
    assert not any(r.ok for r in replies)
    # nothing of it reached the run: no service counted garbage, no recording holds it
    for role, status in report["timing"]["links_received"].items():
        assert status.get("bad", 0) == 0, (role, status)
    for path in (tmp_path / "out" / "recordings").glob("*.mcap"):
        assert not any(b"forged" in m.payload for m in read_episode(path).messages), path


def test_missing_credentials_are_named_before_anything_starts(tmp_path):
    creds = make_credentials(tmp_path / "c", roles=("robot",))  # the other roles have none
    with pytest.raises(CredentialsError, match=r"ft_sensor\.pem: missing"):
        support.runner(support.hold(1), tmp_path / "out", tls=str(creds))
    with pytest.raises(CredentialsError, match="expected an IP address"):
        make_credentials(tmp_path / "d", hosts=("not-an-ip",))
