"""Read datasets: our own format (docs/dataset.md) and EuRoC folders; TUM trajectories; and
write our format frame by frame (``DatasetWriter``, the flight recorder's).

Both readers yield the same frozen types (CameraFrame, RangeSample, AttitudeSample) and the
same calibration objects, so the algorithms run offline on simulated and real recordings alike.
This is I/O (drivers/): the camera's ``folder:`` source and ``companion eval`` read recordings
through it; the simulator writes them (``sitl.dataset.record``), and so does the service's
recorder (``companion run --record DIR``) through ``DatasetWriter``.

A dataset declares what it has: its distance sensors (``[[rangefinders]]`` in
calibration.toml: none declared, none used), a simulated world (a ``[sitl]`` table in
meta.toml: without one ``Dataset.sitl`` is None and nothing may ray cast a world), ground
truth (groundtruth.txt) and the order in which the pipeline was fed (a ``fed_before_frame``
column in ranges.csv / attitude.csv).

The modules:
- ``format``: the format's name, version, columns and value bounds; ``PublishedPose``;
- ``rows``: the CSV rows under the bounded-reading discipline (drivers/safe_files.py);
- ``model``: ``Dataset`` (what a dataset holds, its events in ingest order), ``dataset_steps``;
- ``ours`` and ``euroc``: the two readers; ``detect``: ``open_dataset`` picks one;
- ``tum``: TUM trajectories; ``writer`` and ``toml_text``: ``DatasetWriter`` and its files;
- ``mcap_schemas``, ``mcap_writer``, ``mcap_records``, ``mcap_reader``: a recording as one
  MCAP file (its channels, ``McapDatasetWriter``, the bounded record reader, ``read_mcap``),
  imported only when a recording is MCAP: the service with neither recording nor MCAP
  replays does not load mcap, zstandard or protobuf.
"""

from companion.drivers.dataset.detect import open_dataset
from companion.drivers.dataset.format import FORMAT_NAME, FORMAT_VERSION, PublishedPose
from companion.drivers.dataset.model import Dataset, DatasetStep, check_lens, dataset_steps
from companion.drivers.dataset.rows import read_poses_csv
from companion.drivers.dataset.tum import read_tum, write_tum
from companion.drivers.dataset.writer import DatasetWriter, calibration_tables, write_poses_csv

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Dataset",
    "DatasetStep",
    "DatasetWriter",
    "PublishedPose",
    "calibration_tables",
    "check_lens",
    "dataset_steps",
    "open_dataset",
    "read_poses_csv",
    "read_tum",
    "write_poses_csv",
    "write_tum",
]
