"""Episode datasets: robomimic/MimicGen-style HDF5 files, written crash-safely. h5py + numpy only.

Why this shape:

* The sim worker collects episodes in several processes at once, and a collection run of hours can
  be killed at any moment. So each worker writes **one file per episode** (a *part*) under a parts
  directory, atomically: to a temp name in the same directory, fsync, then ``os.replace``. A part
  file that has its final name is therefore always complete, and no file handle is ever shared
  between processes.
* :func:`consolidate` then builds the one dataset file the trainer reads, again into a temp file
  that is ``os.replace``-d over the output, so the dataset file is never half-written either. An
  existing dataset (a previous run that asked for fewer episodes) is carried over, so a run can be
  extended or resumed: :func:`completed_indices` tells the collector which episodes exist already.
* The layout follows robomimic (``data/demo_<i>/obs/agentview_image``, ``data/demo_<i>/actions``,
  ``data/demo_<i>/states``, ``data.attrs["total"]``), so the usual robomimic/MimicGen tools and
  habits apply. The per-demo label is ``attrs["success"]``.
* Actions are plans in the sense of :mod:`firp.core.contract` and are validated with its one validator
  before anything is written, so a dataset can never hold an action the service would reject.

Attribute values may be ``str``, ``int``, ``float``, ``bool`` or JSON-able containers (lists,
dicts, tuples, ``None``, numpy arrays). Containers are stored as JSON strings (HDF5 attributes hold
no nested structures) and their names listed in the ``_json_attrs`` attribute, so reading decodes
exactly those and a plain string that happens to look like JSON stays a string.
"""

from firp.core.episodes.layout import (
    IMAGE_KEY,
    VIEW_KEY,
    AttrValue,
    EpisodeRecord,
    EpisodeValidationError,
    demo_name,
    part_path,
    validate_record,
)
from firp.core.episodes.reader import EpisodeDataset
from firp.core.episodes.writer import (
    ConsolidationResult,
    completed_indices,
    completed_part_indices,
    consolidate,
    write_episode_part,
)

__all__ = [
    "AttrValue",
    "ConsolidationResult",
    "EpisodeDataset",
    "EpisodeRecord",
    "EpisodeValidationError",
    "IMAGE_KEY",
    "VIEW_KEY",
    "completed_indices",
    "completed_part_indices",
    "consolidate",
    "demo_name",
    "part_path",
    "validate_record",
    "write_episode_part",
]
