"""The MCAP writer's schema texts equal what rosbags generates (``pipeline/writers/msgdefs.py``
keeps them so that a command does not build rosbags' typestore), and cover every type it writes."""

from __future__ import annotations

from rosbags.typesys import Stores, get_typestore

from imupipe.pipeline.writers.mcap import msgdef
from imupipe.pipeline.writers.msgdefs import MSGDEFS
from imupipe.readers.topics import STREAM_TYPES


def test_each_kept_text_is_rosbags_own():
    store = get_typestore(Stores.ROS2_HUMBLE)
    for msgtype, text in MSGDEFS.items():
        assert text == store.generate_msgdef(msgtype, ros_version=2)[0], msgtype


def test_every_type_the_writer_writes_is_kept():
    written = {STREAM_TYPES[s] for s in ("imu", "mag", "temperature")}
    assert written <= set(MSGDEFS)
    assert msgdef("sensor_msgs/msg/FluidPressure").startswith("std_msgs/Header header")  # others
