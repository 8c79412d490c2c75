"""A run's own independent work in a pool of processes (services.runtime.threads.process_map):
the candidate fits of a phase-count selection and the report's reading of recordings
give what one process gives, in order, and an interrupted pool leaves no process behind."""

import json
import os
import time

import numpy as np
import pytest

from etar.selection import vote_order
from etar.synthetic import make_task, sample_demonstrations
from services.results.decoding import EpisodeReading, decode_episode
from services.runtime.threads import process_map
from tests.services.recordings.test_recording import mixed_messages, write_episode


def _pid_and_square(x):
    import sys

    sys.stdout.write(f"piece {x} said this without a newline;")  # held in the process's buffer
    return os.getpid(), x * x


def _fail_on_three(job):
    x, pids = job
    with open(pids, "a") as f:
        f.write(f"{os.getpid()}\n")
    if x == 3:
        raise ValueError("three")
    return x


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _gone(pid: int, within_s: float = 5.0) -> bool:
    """Whether process ``pid`` is gone, or goes within ``within_s``."""
    deadline = time.monotonic() + within_s
    while _alive(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


def test_a_pool_runs_the_pieces_in_other_processes_and_returns_them_in_order(capfd):
    with process_map(2) as pool_map:
        results = list(pool_map(_pid_and_square, range(8)))
    assert [sq for _, sq in results] == [x * x for x in range(8)]
    assert os.getpid() not in {pid for pid, _ in results}
    # they left without the interpreter's teardown (``exit_without_teardown``), what they wrote said
    assert all(_gone(pid) for pid, _ in results)
    out = capfd.readouterr().out
    assert all(f"piece {x} said this" in out for x in range(8)), out
    with process_map(1) as plain:
        assert plain is map


def test_a_failing_piece_raises_in_the_caller_and_the_pool_is_gone(tmp_path):
    pids = tmp_path / "pids"
    with pytest.raises(ValueError, match="three"):
        with process_map(2) as pool_map:
            list(pool_map(_fail_on_three, [(x, str(pids)) for x in range(6)]))
    workers = {int(line) for line in pids.read_text().split()}
    assert workers and os.getpid() not in workers
    assert not [pid for pid in workers if _alive(pid)]


def test_the_per_demonstration_vote_is_the_same_in_a_pool():
    task = make_task(2, seed=3)
    demos = [(s, f) for s, f, _ in sample_demonstrations(task, 3, 300, seed=13)]
    here = vote_order(demos, [1, 2, 3], "bic", seed=0, n_restarts=1, max_iter=40)
    with process_map(2) as pool_map:
        pooled = vote_order(demos, [1, 2, 3], "bic", seed=0, n_restarts=1, max_iter=40, fit_map=pool_map)
    assert pooled.to_dict() == here.to_dict()
    for a, b in zip(here.per_demonstration, pooled.per_demonstration):
        for k in a.models:
            np.testing.assert_array_equal(a.models[k].A, b.models[k].A)
            np.testing.assert_array_equal(a.models[k].W, b.models[k].W)


def test_the_report_reads_recordings_in_a_pool_as_in_one_process(tmp_path, rng):
    readings = []
    for i in range(3):
        path = tmp_path / f"reproduction_{i:02d}.mcap"
        write_episode(path, mixed_messages(80 + 20 * i, rng))
        readings.append(EpisodeReading(str(path), phase_to_truth={0: 0, 1: 1}))
    readings.append(EpisodeReading(str(tmp_path / "missing.mcap")))
    here = list(map(decode_episode, readings))
    with process_map(2) as pool_map:
        pooled = list(pool_map(decode_episode, readings))
    assert not here[-1].readable and not pooled[-1].readable
    for a, b in zip(here[:-1], pooled[:-1]):
        assert a.links == b.links and a.undecodable == b.undecodable
        # NaN where no transition was seen: compared as JSON writes them
        assert json.dumps(a.phases, sort_keys=True) == json.dumps(b.phases, sort_keys=True)
        assert a.phases["updates"] > 0
        for series_a, series_b in zip(a.fri_quality, b.fri_quality):
            np.testing.assert_array_equal(series_a, series_b)


def test_the_learn_stages_pool_reads_each_demonstration_as_it_is_recorded(foxglove_run_dir):
    """services.run.learn.DemonstrationReads: started by the first demonstration of a lockstep run
    whose learn stage chooses the number of phases, it reads each recording in the pool while the
    run goes on; the learn stage gets what reading then would give, and closing ends the workers."""
    from services.run.learn import DemonstrationReads, _reader
    from tests import support

    demo = str(foxglove_run_dir / "recordings" / "demonstration_00.mcap")
    scenario = support.scenario("smoke", {"learn.phases": "auto"})
    assert not DemonstrationReads(support.scenario("smoke", {"learn.phases": 2}), 2).wanted
    assert not DemonstrationReads(support.scenario("smoke", {"learn.phases": "auto", "clock": "realtime"}), 2).wanted
    with DemonstrationReads(scenario, workers=2) as reads:
        reads.read(demo)
        assert reads.pending == (demo,)
        pid, _ = next(reads.work_map(_pid_and_square, [3]))
        assert pid != os.getpid()
        # the first read ahead, the second now: both what one process reads
        got = reads.demonstrations([demo, demo])
        assert reads.pending == ()
        reads.close()
        assert reads.work_map is None and not reads.wanted
    want = _reader(scenario)(demo)
    for d in got:
        assert d.keys() == want.keys()
        for key in ("states", "forces", "phases"):
            np.testing.assert_array_equal(d[key], want[key])
    assert _gone(pid), "the pool's worker outlived close()"


def test_the_reports_recordings_are_decoded_beside_the_run_and_only_a_changed_reading_again(tmp_path, rng):
    """services.run.report_reads.ReportReads: each reading is decoded once in a process under
    SCHED_IDLE as soon as it is known; on a clean exit the report gets what was decoded, and
    ``decode_episodes`` decodes only a reading that is not among them (here one whose phase
    mapping changed since), giving what decoding everything at the end gives."""
    from services.results.decoding import decode_episodes
    from services.run.report_reads import ReportReads

    readings = []
    for i in range(2):
        path = tmp_path / f"reproduction_{i:02d}.mcap"
        write_episode(path, mixed_messages(60 + 20 * i, rng))
        readings.append(EpisodeReading(str(path), phase_to_truth={0: 0, 1: 1}))
    assert ReportReads(False).decoded == [] and ReportReads(False).catch_up(readings) is None
    small = ReportReads(True)  # a smoke's recordings are not worth a process's start
    small.catch_up(readings)
    assert small._map is None and small._started == []
    with ReportReads(True, at_least=0) as ahead:
        ahead.catch_up(readings[:1])
        ahead.catch_up(readings)  # the first is not started twice
        assert [r for r, _ in ahead._started] == readings
        pid, _ = next(ahead._map(_pid_and_square, [2]))
        assert pid != os.getpid() and os.sched_getscheduler(pid) == os.SCHED_IDLE
    assert [r for r, _ in ahead.decoded] == readings
    final = [readings[0], EpisodeReading(readings[1].path, phase_to_truth={0: 1, 1: 0})]
    for a, b in zip(decode_episodes(final, 1, ahead.decoded), map(decode_episode, final)):
        assert a.links == b.links and json.dumps(a.phases, sort_keys=True) == json.dumps(b.phases, sort_keys=True)
    assert decode_episodes(final, 1, ahead.decoded)[0] is ahead.decoded[0][1]  # taken, not decoded again
    assert _gone(pid), "the decoding process outlived the run"


def _slow_square(x):
    time.sleep(1.0)
    return x * x


def test_the_recordings_the_process_beside_has_not_begun_are_decoded_here_from_the_end(tmp_path, rng):
    """When the reads end, this process takes back from the end of the queue what the process
    beside has not begun and decodes it itself while that one goes on from the front: every
    reading decoded once, in order, the same as decoding it here."""
    from services.run.report_reads import ReportReads

    readings = []
    for i in range(5):
        path = tmp_path / f"reproduction_{i:02d}.mcap"
        write_episode(path, mixed_messages(40 + 10 * i, rng))
        readings.append(EpisodeReading(str(path), phase_to_truth={0: 0, 1: 1}))
    with ReportReads(True, at_least=0) as reads:
        assert reads.start("busy", _slow_square, (3,), readings)  # the process beside busy for a second
        reads.catch_up(readings)
    # the executor hands a process at most two pieces ahead: the other three were taken back
    assert reads.taken_back >= 3 and reads.ahead == {"busy": 9}
    assert [r for r, _ in reads.decoded] == readings
    for (_, got), reading in zip(reads.decoded, readings):
        want = decode_episode(reading)
        assert got.links == want.links and json.dumps(got.phases, sort_keys=True) == json.dumps(want.phases, sort_keys=True)


def test_a_failed_run_ends_the_report_reads_at_once(tmp_path, rng):
    from services.run.report_reads import ReportReads

    path = tmp_path / "reproduction_00.mcap"
    write_episode(path, mixed_messages(60, rng))
    with pytest.raises(RuntimeError, match="the run failed"):
        with ReportReads(True, at_least=0) as ahead:
            ahead.catch_up([EpisodeReading(str(path))])
            pid, _ = next(ahead._map(_pid_and_square, [2]))
            raise RuntimeError("the run failed")
    assert ahead.decoded == []
    assert _gone(pid)


def _sigint_handling(_):
    import signal

    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN, signal.SIGINT in blocked


def test_a_pools_processes_start_with_sigint_blocked_and_then_ignore_it():
    """A second Ctrl-C to the process group while a pool's processes start must not kill one
    half-way through its start-up (the report was lost to a BrokenProcessPool): the pool
    hands its work over with SIGINT blocked, so its processes start with it blocked, and
    each ignores it once started; here the mask is as it was."""
    import signal

    from services.runtime.threads import _spawning

    seen = []
    got = _spawning(lambda fn, items: seen.append(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))
                    or [fn(x) for x in items], lambda x: x + 1, [1, 2])
    assert got == [2, 3] and seen == [True]
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    with process_map(2) as pool_map:
        assert set(pool_map(_sigint_handling, range(4))) == {(True, False)}


def test_the_votes_fits_of_a_demonstration_run_as_it_is_read_and_the_vote_takes_them(foxglove_run_dir):
    """With the per-demonstration vote, DemonstrationReads fits each demonstration's
    candidates in the pool as soon as it is read; the vote then takes those models instead
    of fitting again, and chooses and fits exactly what it chooses and fits without them."""
    from etar.selection import fit_order
    from services.run.learn import DemonstrationReads, _reader

    demo = str(foxglove_run_dir / "recordings" / "demonstration_00.mcap")
    changes = {"learn.phases": "auto", "learn.candidates": [1, 2], "learn.max_iter": 15, "learn.restarts": 1}
    scenario = support_scenario("smoke", changes)
    assert DemonstrationReads(support_scenario("smoke", {**changes, "learn.selection": "pooled"}), 2)._vote is None
    stage = next(s for s in scenario.stages if s.kind == "learn")
    options = dict(transitions=stage.transitions[0], seed=stage.seed, max_iter=stage.max_iter, n_restarts=1)
    with DemonstrationReads(scenario, workers=2) as reads:
        reads.read(demo)
        (got,) = reads.demonstrations([demo])
        assert len(reads.fitted) == 2  # K=1 and K=2, fitted ahead
        ahead_model, ahead_vote = fit_order([(got["states"], got["forces"])] * 2, [1, 2], "bic", fit_map=reads.fit_map,
                                            **options)
        assert len(reads.fitted) == 0  # the first demonstration's taken, the copy's fitted now
    want = _reader(scenario)(demo)
    model, vote = fit_order([(want["states"], want["forces"])] * 2, [1, 2], "bic", **options)
    assert ahead_vote == vote

    def parameters(m):  # the model file's content, without the fit's wall time
        return json.dumps({k: v for k, v in m.to_dict().items() if k != "fit"}, sort_keys=True)

    assert parameters(ahead_model) == parameters(model)


def support_scenario(name, changes):
    from tests import support

    return support.scenario(name, changes)


def test_the_learning_figures_drawn_beside_a_run_are_those_drawn_after_it(foxglove_run_dir, tmp_path):
    """A run draws the demonstrations' and the learning's figures beside its reproductions
    (``ReportReads.start``, ``learning_figures``) from the learner's arrays; its figures at the
    end then add the reproduction's and keep them: the same files, byte for byte, as drawing
    everything after the run from its folder."""
    import shutil

    from services.results.figures import in_run, learning_figures
    from services.results.figures.phases import world_of_run
    from services.results.folder import read_report
    from services.results.html import write_figures_and_page
    from services.run.learn import _reader
    from services.run.report_reads import ReportReads
    from tests import support

    after, beside = tmp_path / "after", tmp_path / "beside"
    for run_dir in (after, beside):
        shutil.copytree(foxglove_run_dir, run_dir)
        shutil.rmtree(run_dir / "figures", ignore_errors=True)
    report = read_report(beside)
    demos = [str(in_run(beside, d["path"])) for d in report["demonstrations"]]
    arrays = [_reader(support.scenario("smoke", {}))(p) for p in demos]
    job = (str(beside), report["learning"]["model"], world_of_run(beside, demos[:1]), demos, arrays,
           report["learning"]["selection"])
    assert not ReportReads(False).start("figures", learning_figures, job, [])
    with ReportReads(True, at_least=0) as reads:
        assert reads.start("figures", learning_figures, job, [])
        assert reads.start("broken", _fail_on_three, ((3, str(tmp_path / "pids")),), [])
    assert "broken" not in reads.ahead  # a failure there: the figures at the end do it all
    written, skipped, damaged = reads.ahead["figures"]
    assert sorted(p.name for p in written) == sorted(p.name for p in (beside / "figures").glob("*.png"))
    assert "reproduction_00_force_phase_alpha.png" not in {p.name for p in written} and not damaged

    write_figures_and_page(beside, ahead=reads.ahead["figures"])
    write_figures_and_page(after)
    drawn = sorted(p.name for p in (after / "figures").glob("*.png"))
    assert "reproduction_00_force_phase_alpha.png" in drawn and len(drawn) > len(written)
    assert sorted(p.name for p in (beside / "figures").glob("*.png")) == drawn
    for name in drawn:
        assert (beside / "figures" / name).read_bytes() == (after / "figures" / name).read_bytes(), name
    assert (beside / "figures.skipped").read_text() == (after / "figures.skipped").read_text() and skipped


def test_the_report_reads_process_killed_mid_run_costs_the_run_nothing(tmp_path, rng):
    """The process beside the run (SCHED_IDLE, killable by anyone, the OOM killer first) dies:
    the run must go on (it failed with BrokenProcessPool), saying so once; what the process
    had not done is done in the run's process when the reads end, the same results."""
    import signal

    from services.run.report_reads import ReportReads

    readings = []
    for i in range(2):
        path = tmp_path / f"reproduction_{i:02d}.mcap"
        write_episode(path, mixed_messages(60, rng))
        readings.append(EpisodeReading(str(path)))
    said = []
    with ReportReads(True, at_least=0, say=said.append) as reads:
        reads.catch_up(readings[:1])
        pid, _ = next(reads._map(_pid_and_square, [2]))
        os.kill(pid, signal.SIGKILL)
        assert _gone(pid)
        time.sleep(0.5)  # the pool notices its worker is gone
        reads.catch_up(readings)
        assert reads.start("figures", _pid_and_square, (3,), readings)
    assert [r for r, _ in reads.decoded] == readings
    for (_, got), reading in zip(reads.decoded, readings):
        want = decode_episode(reading)
        assert got.links == want.links and json.dumps(got.phases, sort_keys=True) == json.dumps(want.phases, sort_keys=True)
    assert reads.ahead["figures"] == (os.getpid(), 9)  # done here, after the loss
    assert len(said) == 1 and "the report's reader beside the run lost a process (BrokenProcessPool" in said[0], said


def _square_but_die_in_a_worker(job):
    x, parent = job
    if x == 2 and os.getpid() != parent:
        import signal

        os.kill(os.getpid(), signal.SIGKILL)  # as the OOM killer would, mid-piece
    return x * x


def test_a_pool_that_loses_a_worker_mid_map_finishes_the_map_in_this_process():
    """FallbackMap: the pieces returned before the pool broke stand, the rest are done here,
    in order, and the loss is said once; a map after it runs here from the start."""
    from services.runtime.threads import FallbackMap

    said = []
    with process_map(2) as pool_map:
        work_map = FallbackMap(pool_map, said.append, "the test's pool")
        assert list(work_map(_square_but_die_in_a_worker, [(x, os.getpid()) for x in range(6)])) == \
            [0, 1, 4, 9, 16, 25]
        assert list(work_map(_pid_and_square, [3, 4])) == [(os.getpid(), 9), (os.getpid(), 16)]
    assert len(said) == 1 and said[0].startswith("the test's pool lost a process (BrokenProcessPool")


def test_the_learn_stages_pool_killed_mid_fit_costs_the_run_nothing(foxglove_run_dir):
    """The learn stage's pool loses its processes while they read and fit a demonstration
    (killed by anyone, the OOM killer first): the stage reads and fits it in this process,
    says so once, and chooses and fits the same model (it failed the run with
    BrokenProcessPool)."""
    import signal

    from etar.selection import fit_order
    from services.run.learn import DemonstrationReads, _reader

    demo = str(foxglove_run_dir / "recordings" / "demonstration_00.mcap")
    changes = {"learn.phases": "auto", "learn.candidates": [1, 2], "learn.max_iter": 15, "learn.restarts": 1}
    scenario = support_scenario("smoke", changes)
    stage = next(s for s in scenario.stages if s.kind == "learn")
    options = dict(transitions=stage.transitions[0], seed=stage.seed, max_iter=stage.max_iter, n_restarts=1)
    said = []
    with DemonstrationReads(scenario, workers=2, say=said.append) as reads:
        reads.read(demo)
        pool = reads.work_map._pool  # process_map's PoolMap: the executor
        workers = list(pool._processes.values())
        for process in workers:
            os.kill(process.pid, signal.SIGKILL)
        assert all(_gone(process.pid) for process in workers)
        (got,) = reads.demonstrations([demo])
        model, vote = fit_order([(got["states"], got["forces"])], [1, 2], "bic", fit_map=reads.fit_map, **options)
    assert len(said) == 1 and "BrokenProcessPool" in said[0] and "done in this process" in said[0]
    want = _reader(scenario)(demo)
    model_here, vote_here = fit_order([(want["states"], want["forces"])], [1, 2], "bic", **options)
    assert vote == vote_here
    assert json.dumps({k: v for k, v in model.to_dict().items() if k != "fit"}, sort_keys=True) == \
        json.dumps({k: v for k, v in model_here.to_dict().items() if k != "fit"}, sort_keys=True)
