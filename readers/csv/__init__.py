"""CSV and blank-separated text: layout detection, exact time stamps, the reader.

May import: the readers' shared bottom only.

Its modules (the public face). Importing the package imports none of them, so that
the command line starts light and no circle can form: import each by its full name.

- :mod:`imupipe.readers.csv.exact_time`: Time stamps written as text into int64 nanoseconds,...
- :mod:`imupipe.readers.csv.layout`: Where a CSV's data start and how its lines split, found...
- :mod:`imupipe.readers.csv.reader`: CSV (and blank-separated text, e.g.
"""

__all__ = ["exact_time", "layout", "reader"]
