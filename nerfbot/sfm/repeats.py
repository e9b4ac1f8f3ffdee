"""Features of a texture that repeats within one image, found and dropped before matching.

A tiled floor or a table printed from one tile shows the same patch many times in each view. A
SIFT feature on it matches every copy in another view equally well; where the other view shows
only some copies, the ratio test cannot tell, and matches to the wrong copy agree with one
another: two-view verification keeps them (a plane seen twice admits the shifted geometry) and
the mapper can register whole groups of views a period of the pattern away. A feature whose
descriptor has a near twin elsewhere in its own image is such a feature; dropping it before
matching leaves the ones that say where they are (objects, shadows, edges, the pattern's
borders). The same idea as rejecting ambiguous matches by the ratio test, applied within one
image rather than between two.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

#: Two features closer than this in their own image (pixels) are one detection (SIFT reports a
#: blob at several orientations and nearby positions), never copies of a pattern.
MIN_SEPARATION_PX = 8.0
#: Rows of the (N, N) descriptor distance matrix computed at once (memory: CHUNK x N x 4 bytes).
CHUNK = 2048


def nearest_twin_distance(xy: np.ndarray, descriptors: np.ndarray,
                          min_separation_px: float = MIN_SEPARATION_PX) -> np.ndarray:
    """(N,) distance from each feature's descriptor to the closest descriptor of another
    feature of the same image at least ``min_separation_px`` away.

    Args:
        xy: (N, 2) keypoint positions, pixels.
        descriptors: (N, D) descriptors (any scale: each is normalised to unit length, as
            COLMAP's SIFT matcher compares them).
        min_separation_px: closer keypoints are not compared.

    Returns:
        (N,) unit-descriptor L2 distances in [0, 2]; 2 where no other feature is far enough.
    """
    n = len(xy)
    if len(descriptors) != n:
        raise ValueError(f"{n} keypoints but {len(descriptors)} descriptors")
    unit = np.asarray(descriptors, np.float32)
    unit = unit / np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-12)
    # pairs too close to compare, both ways round, and each feature with itself
    close = cKDTree(np.asarray(xy, np.float64)).query_pairs(min_separation_px,
                                                            output_type="ndarray")
    close = np.concatenate([close, close[:, ::-1], np.repeat(np.arange(n)[:, None], 2, 1)])
    out = np.full(n, 2.0, np.float32)
    for start in range(0, n, CHUNK):
        stop = min(start + CHUNK, n)
        squared = np.maximum(2.0 - 2.0 * (unit[start:stop] @ unit.T), 0.0)
        inside = close[(close[:, 0] >= start) & (close[:, 0] < stop)]
        squared[inside[:, 0] - start, inside[:, 1]] = 4.0
        out[start:stop] = np.sqrt(squared.min(1))
    return out


def drop_repeated_features(database: Path, max_twin_distance: float,
                           min_separation_px: float = MIN_SEPARATION_PX) -> dict:
    """Remove, in COLMAP's ``database`` before matching, every feature whose descriptor has a
    twin in its own image (:func:`nearest_twin_distance` under ``max_twin_distance``).

    Returns:
        {"features": features before, "kept": features after, "per_image_kept_min": the
        fewest kept by one image}.
    """
    db = pycolmap.Database.open(str(database))
    try:
        features = {image.image_id: (db.read_keypoints(image.image_id),
                                     db.read_descriptors(image.image_id))
                    for image in db.read_all_images()}
        # the database can add rows, not shorten them: clear both tables and write them again
        db.clear_keypoints()
        db.clear_descriptors()
        before = kept = 0
        fewest = None
        for image_id, (keypoints, descriptors) in features.items():
            keep = nearest_twin_distance(keypoints[:, :2], descriptors.data,
                                         min_separation_px) >= max_twin_distance
            before += len(keep)
            kept += int(keep.sum())
            fewest = int(keep.sum()) if fewest is None else min(fewest, int(keep.sum()))
            db.write_keypoints(image_id, np.ascontiguousarray(keypoints[keep]))
            db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                descriptors.type, np.ascontiguousarray(descriptors.data[keep])))
    finally:
        db.close()
    return {"features": before, "kept": kept, "per_image_kept_min": fewest or 0}
