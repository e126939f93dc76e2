"""The oposm MCAP dataset format: one `oposm.Step` protobuf message per step, metadata records.

A dataset file holds a `DatasetInfo` (metadata `oposm.dataset`), the steps of all episodes on the
topic `/demo/step` (log time = simulated time) and the episode lengths (metadata `oposm.episodes`).
Any MCAP tool can decode it: the protobuf schema is embedded. See docs/development.md, "Contracts",
and docs/data.md, "The MCAP file".
"""

from pipeline.recording.reader import iter_episodes, read_episodes, read_info
from pipeline.recording.schema import FORMAT_VERSION, SCHEMA_NAME, TOPIC, Step
from pipeline.recording.summary import format_summary, summarize
from pipeline.recording.writer import WriteSummary, write_dataset

__all__ = [
    "FORMAT_VERSION",
    "SCHEMA_NAME",
    "TOPIC",
    "Step",
    "WriteSummary",
    "format_summary",
    "iter_episodes",
    "read_episodes",
    "read_info",
    "summarize",
    "write_dataset",
]
