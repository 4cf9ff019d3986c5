"""MCAP: its records, the chunk-level parser, the summary section, the reader.

May import: the readers' shared bottom (table, errors, spec, topics, decoded, sources, cdr,
compression) and ``ros1`` (ROS 1 encoded MCAP).

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.mcap.fast`: MCAP at the chunk level: records, channels, and each chunk's...
- :mod:`imupipe.readers.mcap.reader`: MCAP logs (ROS 2 CDR or ROS 1 encoded) into the common...
- :mod:`imupipe.readers.mcap.records`: The MCAP records imupipe reads and writes itself, field by...
- :mod:`imupipe.readers.mcap.summary`: What an MCAP file holds, from its summary section alone:...
"""

__all__ = ["fast", "reader", "records", "summary"]
