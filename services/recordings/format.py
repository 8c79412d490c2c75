"""The recording format: one MCAP file per episode (a demonstration or a reproduction).

Each topic is a channel with ``message_encoding="json"`` and a ``jsonschema`` schema
taken from ``services.runtime.messages`` (Foxglove opens the files as they are); the
payload is written unchanged, so a recording is exactly what crossed the wire.

Times are integer nanoseconds.  ``log_time`` is the recorder's receive time on
CLOCK_MONOTONIC; ``publish_time`` is the message's ``sent_ns`` header (the same
clock, on one host), or the receive time when the payload does not decode.  The
``etar`` metadata record states this epoch.

Layout, chosen so a killed recorder loses little: the header, the ``etar``
metadata record and the ``scenario.yaml`` attachment come first; messages
follow in zstd chunks of about ``CHUNK_SIZE`` (160 KiB) of records; the summary (statistics, chunk and
message indexes) is written by ``finish()``.  Indexes are written only for
groups that cannot be empty (chunks, messages, metadata, and attachments when
there is a scenario): mcap's default writer emits summary offsets for empty
groups, which MCAP validators flag.
"""

from services.runtime.messages import EPISODE_SUMMARY, RUNNER_EVENT, SERVICE_LOG

# bytes of uncompressed records per chunk: what a killed recorder can lose.  A
# reproduction records 1.94 MB per simulated second, a demonstration 1.60 MB
# (smoke scenario over Zenoh), so a chunk holds 84 ms or 102 ms of the episode
CHUNK_SIZE = 160 * 1024
METADATA_NAME = "etar"
SCENARIO_ATTACHMENT = "scenario.yaml"
SCENARIO_MEDIA_TYPE = "application/yaml"
MAGIC = b"\x89MCAP0\r\n"


class RecordingError(ValueError):
    """A recording that cannot be written or read, naming the file and what is wrong."""


# topics whose payloads carry wall-clock durations and loop timing, and the services' log lines
# (when a service logs is the machine's doing): not what a seed determines
WALL_CLOCK_TOPICS = frozenset({EPISODE_SUMMARY.channel, RUNNER_EVENT.channel, SERVICE_LOG.channel})
