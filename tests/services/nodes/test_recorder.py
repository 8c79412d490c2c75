"""The recorder node as a function of the samples it takes."""

import pytest

from services.nodes.recorder import RecorderConfig, RecorderNode
from services.recordings.format import RecordingError


def test_a_sample_its_file_cannot_take_still_counts_as_arrived(tmp_path):
    """A full disk: the file takes no more, so ending the episode must not wait for
    samples that arrived and could not be written (it waited out the recorder's 10 s)."""
    recorder = RecorderNode(RecorderConfig(out_dir=str(tmp_path)), None, None, run_id="full")
    try:
        recorder.begin({"path": "d.mcap", "kind": "demonstration", "index": 0})
        recorder.on_sample("robot/state", 1, b'{"seq":1,"stamp_ns":1000000}')

        def full(*_):
            raise RecordingError("d.mcap: could not be written (No space left on device; 0 B free)")

        recorder.writer.add = full
        with pytest.raises(RecordingError):
            recorder.on_sample("robot/state", 2, b'{"seq":2,"stamp_ns":2000000}')
        assert recorder.last_seq == {"robot/state": 2}
        assert recorder.lagging(["robot/state"], 2) == []
        assert recorder.total == 1
    finally:
        del recorder.writer.add  # the file finishes with what it took
        recorder.close()
    assert (tmp_path / "d.mcap").exists()
