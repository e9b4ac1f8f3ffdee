"""Posed-image datasets: readers for nerfstudio, instant-ngp, Blender and D-NeRF layouts.

``load_dataset(path)`` returns a validated :class:`Dataset`; malformed input raises
:class:`DatasetError` naming the file and the field.
"""

from nerfbot.data.bounds import estimate_bounds_from_cameras
from nerfbot.data.dataset import Dataset
from nerfbot.data.errors import DatasetError
from nerfbot.data.readers import load_dataset

__all__ = ["Dataset", "DatasetError", "estimate_bounds_from_cameras", "load_dataset"]
