"""COLMAP's INFO log kept off the console while warnings, errors and progress bars show.

pycolmap (4.x) writes a glog line for every step of feature extraction, matching, mapping and
bundle adjustment (with multi-line solver reports) straight to the process's stderr, hundreds
per reconstruction, and its log-level settings (``pycolmap.logging.minloglevel``,
``GLOG_minloglevel``) do not filter them.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from typing import Iterator, TextIO

#: The first line of a glog record: an optional colour code, the severity letter, date, time,
#: thread id and source location, e.g. ``I20261208 04:45:12.613309 1402 bundle_adjustment.cc:46] ``.
_GLOG_RECORD = re.compile(rb"(?:\x1b\[[0-9;]*m)*([IWEF])\d{8} \d\d:\d\d:\d\d\.\d+ +\d+ \S+:\d+\] ")


def drop_info_records(text: bytes) -> bytes:
    """``text`` without its glog INFO records: a line starting an I record and the indented or
    blank lines that continue it (a bundle-adjustment report). Warning, error and fatal records,
    their continuation lines and every other line are kept as they are."""
    kept = []
    in_info = False
    for line in text.splitlines(keepends=True):
        record = _GLOG_RECORD.match(line)
        if record:
            in_info = record.group(1) == b"I"
        elif in_info and (not line.strip() or line[:1] in (b" ", b"\t")):
            continue
        else:
            in_info = False
        if not in_info:
            kept.append(line)
    return b"".join(kept)


@contextlib.contextmanager
def quiet_colmap() -> Iterator[TextIO]:
    """While the block runs, file descriptor 2 (where COLMAP logs) goes to an anonymous
    temporary file; on exit the file's content without INFO records
    (:func:`drop_info_records`) is written to the real stderr. Python's own writes to stderr in
    the block arrive then too, in order. Yields a text stream on the real stderr for what must
    show while COLMAP works (progress bars); it is closed on exit."""
    sys.stderr.flush()
    saved = os.dup(2)
    console = os.fdopen(os.dup(saved), "w", buffering=1)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            yield console
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            console.close()
            captured.seek(0)
            kept = drop_info_records(captured.read())
            if kept:
                with os.fdopen(os.dup(2), "wb") as err:
                    err.write(kept)
