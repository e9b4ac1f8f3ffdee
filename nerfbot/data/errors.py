"""The one exception type raised for malformed datasets."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or inconsistent.

    The message always starts with the offending file and, when there is one, the JSON field,
    e.g. ``/data/scene/transforms.json: frames[3].transform_matrix: pose contains NaN``.
    """
