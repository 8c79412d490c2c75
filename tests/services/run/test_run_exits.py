"""A service that does not end by itself when a run asks it to is the run's failure, named
(services.run.runner._unclean_exits): serve had exited 0 with 'error: null' after its
ft_sensor was SIGKILLed at shutdown."""

from services.run.runner import _unclean_exits


def test_a_service_ended_by_a_signal_or_an_error_code_is_named():
    assert _unclean_exits({"robot": 0, "ft_sensor": 0, "recorder": None}, {}) == ""
    said = _unclean_exits({"robot": 0, "ft_sensor": -9, "recorder": 3}, {})
    assert said == ("ft_sensor did not exit when asked and was ended by SIGKILL (exit code -9); "
                    "recorder exited with code 3")
    # a service lost during the run is the run's error already, not said twice
    assert _unclean_exits({"phase_estimator": -9, "robot": 0}, {"phase_estimator": 12.5}) == ""
