"""Files and messages: the MagneticField CDR codec, rosbag2 reading and writing, CSV
recordings, calibration and truth files, crash-safe writes and topic names. Everything that
reads input turns a failure into one :class:`~magcal_ros.errors.InputError` line."""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "open_recording": "magcal_ros.io.recordings",
        "read_bag_sets": "magcal_ros.io.bag_reader",
        "read_csv": "magcal_ros.io.csv_recording",
        "read_recording": "magcal_ros.io.recordings",
        "SideTopics": "magcal_ros.io.recordings",
        "with_bag_currents": "magcal_ros.io.recordings",
        "with_bag_imu": "magcal_ros.io.recordings",
        "with_bag_side_streams": "magcal_ros.io.recordings",
        "with_bag_temperatures": "magcal_ros.io.recordings",
        "write_csv": "magcal_ros.io.csv_recording",
        "write_recording_bag": "magcal_ros.io.bag_writer",
    },
)
