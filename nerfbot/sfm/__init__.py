"""Camera poses from images: structure from motion with pycolmap, written as a dataset.

:func:`nerfbot.sfm.pipeline.run_sfm` recovers cameras; :mod:`nerfbot.sfm.dataset` turns a folder
of images or an existing dataset into a posed nerfstudio dataset (``nerfbot colmap``).
"""
