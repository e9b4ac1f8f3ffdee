"""Structure from motion with pycolmap, in two stages. First the poses, from the SIFT features
that have no twin in their own image (a texture repeated within a view misleads matching,
:mod:`nerfbot.sfm.repeats`): exhaustive or sequential matching guided by each pair's two-view
geometry, incremental mapping (the best of a few runs), then a refinement that COLMAP's
defaults leave out. Then precision, from every feature: the verified pairs matched again,
triangulated with those poses and refined the same way.

COLMAP's mapper keeps observations up to 4 px from their projection and bundle-adjusts with a
squared loss, thresholds chosen for photographs thousands of pixels wide. On the small images a
robot camera or a simulator gives (128-512 px), those mismatches bias the poses by a degree or
more. :func:`refine_reconstruction` drops observations beyond ``max_reproj_error_px`` and
re-adjusts with a Cauchy loss until the set is stable (measured in BENCHMARKS, "Poses from
images"); with known intrinsics they stay fixed throughout.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pycolmap
from tqdm.auto import tqdm

from nerfbot.data.colmap import cam_from_world_from_c2w, require_pycolmap
from nerfbot.sfm.console import quiet_colmap
from nerfbot.sfm.repeats import drop_repeated_features

log = logging.getLogger(__name__)

MATCHERS = ("exhaustive", "sequential")
#: Observations seen under less than this triangulation angle (degrees) fix no depth.
MIN_TRIANGULATION_ANGLE_DEG = 1.5
#: An image keeps its pose only while this many of its observations survive refinement, as many
#: inliers as registration asked (COLMAP's ``abs_pose_min_num_inliers``): a view registered 180
#: degrees off on a symmetric table rests on a few matches of its repeated texture with views
#: from the opposite side (15-25 on the tabletop at 1024 px, where the median image keeps 234).
MIN_IMAGE_POINTS = 30
#: ... and this share of the median registered image's observations.
MIN_IMAGE_POINTS_SHARE = 0.1
#: A verified match agrees with the recovered poses within this Sampson distance, pixels.
AGREEMENT_MAX_ERROR_PX = 2.0
#: Below this share of verified pairs agreeing with the recovered poses, the matches are
#: dominated by a repeated texture: sound models measured 0.6-1.0 (0.6: the glassware's distinct
#: features), the glassware with every feature kept 0.07-0.10 (BENCHMARKS, "Poses from images").
MIN_PAIRS_AGREEING = 0.5
#: Default :attr:`SfmOptions.drop_repeated`: on the glassware capture's table, printed from one
#: tile, 0.3 left 3 of 67 views a tile away and 0.4 none (BENCHMARKS, "Poses from images").
DROP_REPEATED = 0.4


@dataclass(frozen=True)
class CameraPrior:
    """Intrinsics shared by every image, in COLMAP's model and parameter order.

    Attributes:
        model: "PINHOLE" (fx, fy, cx, cy) or "OPENCV" (fx, fy, cx, cy, k1, k2, p1, p2).
        params: the model's parameters, pixels (principal point with pixel centres at +0.5).
        fixed: keep them fixed (known calibration) rather than refine them.
    """

    model: str
    params: tuple
    fixed: bool = True


@dataclass
class SfmOptions:
    """Choices of :func:`run_sfm`.

    Attributes:
        matcher: "exhaustive" (every pair; best up to a few hundred images) or "sequential"
            (each image with its ``sequential_overlap`` successors, for video-like captures).
        max_reproj_error_px: refinement drops observations farther than this from their
            projection, pixels.
        refine_rounds: filter + bundle-adjustment rounds after mapping (0 = COLMAP's result).
        seed: pycolmap's random seed (RANSAC, mapper), for repeatable runs.
        threads: worker threads (-1 = all cores).
        sequential_overlap: successors matched by the sequential matcher.
        mapper_runs: incremental mapping runs (seeds ``seed``, ``seed + 1``, ...); the model
            that explains the most verified matches is kept. On repeated texture a run can
            fold the model (groups of cameras consistent among themselves, tens of degrees
            off from each other); another start avoids it.
        guided_matching: match each verified pair again along the two-view geometry found,
            which keeps correct matches the ratio test rejects on repetitive texture: longer
            tracks and closer poses for more matching time (BENCHMARKS, "Poses from images").
        drop_repeated: features whose descriptor has a twin in its own image closer than this
            (L2 distance of unit descriptors, 0-2) are dropped before matching: a texture that
            repeats within a view (a tiled floor, a table printed from one tile) matches the
            wrong copy in another view (:mod:`nerfbot.sfm.repeats`). 0 keeps every feature.
            With known poses (:func:`triangulate_known_poses`) the poses cannot be misled,
            but a wrong copy matched along an epipolar line still triangulates, and with two
            views nothing outvotes it (a sixth to a third of two-view keypoints decimetres
            off); dropping them did not raise two-view PSNR (one seed), so known poses keep
            every feature by default (BENCHMARKS, "How right the keypoints are").
        refine_all_features: with ``drop_repeated``, once the views are posed from the
            distinct features, match every feature of the pairs verified, triangulate with
            those poses and bundle-adjust again (:func:`_refine_with_every_feature`): the
            distinct features choose the poses, all of them make them precise.
    """

    matcher: str = "exhaustive"
    max_reproj_error_px: float = 1.0
    refine_rounds: int = 3
    seed: int = 0
    threads: int = -1
    sequential_overlap: int = 10
    mapper_runs: int = 2
    guided_matching: bool = True
    drop_repeated: float = DROP_REPEATED
    refine_all_features: bool = True

    def check(self) -> None:
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher: expected one of {', '.join(MATCHERS)}, got "
                             f"{self.matcher!r}")
        if not self.max_reproj_error_px > 0:
            raise ValueError(f"max_reproj_error_px: must be > 0, got {self.max_reproj_error_px}")
        if self.mapper_runs < 1:
            raise ValueError(f"mapper_runs: must be >= 1, got {self.mapper_runs}")
        if not 0.0 <= self.drop_repeated <= 2.0:
            raise ValueError(f"drop_repeated: must be in [0, 2], got {self.drop_repeated}")
        if self.refine_rounds < 0:
            raise ValueError(f"refine_rounds: must be >= 0, got {self.refine_rounds}")


@dataclass
class SfmResult:
    """A reconstruction and what it took.

    Attributes:
        reconstruction: the largest model pycolmap found (COLMAP's frame and scale).
        registered: names of the images with a pose, sorted.
        unregistered: names of the images left out.
        seconds: phase -> wall-clock seconds ("features", "repeats", "matching", "mapping",
            "refinement", "all_features", "total").
        models: how many separate models the mapper produced (1 when every registered image
            connects).
        deregistered: images the mapper posed but the refinement removed (too few surviving
            observations).
        inlier_matches: feature matches the two-view geometries verified, over all pairs.
        mapper_runs: per mapping run, its seed, registered images and the verified matches
            its largest model explains (both ends observations of one 3D point).
        agreement: how far the verified matches agree with the recovered poses
            (:func:`pose_agreement`), or None when not measured.
        features: {"features": SIFT features extracted, "kept": those matched} (fewer with
            ``drop_repeated``).
    """

    reconstruction: "pycolmap.Reconstruction"
    registered: list[str]
    unregistered: list[str]
    seconds: dict = field(default_factory=dict)
    models: int = 1
    deregistered: list = field(default_factory=list)
    inlier_matches: int = 0
    mapper_runs: list = field(default_factory=list)
    agreement: Optional[dict] = None
    features: dict = field(default_factory=dict)

    def summary(self) -> dict:
        rec = self.reconstruction
        return {
            "images": len(self.registered) + len(self.unregistered),
            "registered": len(self.registered),
            "unregistered": self.unregistered,
            "models": self.models,
            "deregistered": self.deregistered,
            "inlier_matches": self.inlier_matches,
            "mapper_runs": self.mapper_runs,
            "points": int(rec.num_points3D()),
            "mean_track_length": float(rec.compute_mean_track_length()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "agreement": self.agreement,
            "features": dict(self.features),
            "seconds": dict(self.seconds),
        }


def _bundle_options(refine_intrinsics: bool, threads: int) -> "pycolmap.BundleAdjustmentOptions":
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = refine_intrinsics
    options.refine_extra_params = refine_intrinsics
    options.refine_principal_point = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 1.0  # pixels
    solver = options.ceres.solver_options
    solver.max_num_iterations = 200
    solver.function_tolerance = 1e-10
    solver.gradient_tolerance = 1e-10
    solver.parameter_tolerance = 1e-10
    solver.num_threads = threads
    return options


def refine_reconstruction(rec: "pycolmap.Reconstruction", max_reproj_error_px: float,
                          rounds: int, refine_intrinsics: bool = False,
                          threads: int = -1, fixed_poses: bool = False
                          ) -> tuple[list[int], list[str]]:
    """Filter observations beyond ``max_reproj_error_px`` and bundle-adjust with a Cauchy loss,
    ``rounds`` times, in place. An image left with fewer than :data:`MIN_IMAGE_POINTS`
    observations, or than :data:`MIN_IMAGE_POINTS_SHARE` of the median image's, is
    deregistered: its pose rested on mismatches (a table's 180-degree symmetry
    registers such images 110-180 degrees off). With ``fixed_poses`` (known cameras) only
    the points move and no image is deregistered.

    Returns:
        (observations dropped per round, names of the images deregistered).
    """
    dropped, removed = [], []
    options = _bundle_options(refine_intrinsics, threads)
    options.refine_rig_from_world = not fixed_poses
    for _ in range(rounds):
        manager = pycolmap.ObservationManager(rec)
        dropped.append(int(manager.filter_all_points3D(max_reproj_error_px,
                                                       MIN_TRIANGULATION_ANGLE_DEG)))
        weak = [] if fixed_poses else _weak_images(rec)
        for im in weak:
            removed.append(im.name)
            manager.deregister_frame(im.frame_id)
        pycolmap.bundle_adjustment(rec, options)
    return dropped, removed


def _weak_images(rec: "pycolmap.Reconstruction") -> list:
    """Registered images with too few observations to trust their pose (see
    :func:`refine_reconstruction`)."""
    posed = [im for im in rec.images.values() if im.has_pose]
    if not posed:
        return []
    counts = sorted(im.num_points3D for im in posed)
    floor = max(MIN_IMAGE_POINTS, MIN_IMAGE_POINTS_SHARE * counts[len(counts) // 2])
    return [im for im in posed if im.num_points3D < floor]


def _reader_options(camera: Optional[CameraPrior]) -> "pycolmap.ImageReaderOptions":
    options = pycolmap.ImageReaderOptions()
    if camera is not None:
        options.camera_model = camera.model
        options.camera_params = ",".join(repr(float(p)) for p in camera.params)
    else:
        options.camera_model = "SIMPLE_RADIAL"
    return options


def _matching_options(options: SfmOptions, threads: int) -> "pycolmap.FeatureMatchingOptions":
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.guided_matching = options.guided_matching
    return matching


def _features_and_matches(database: Path, image_dir: Path, names: list[str],
                          camera: Optional[CameraPrior], options: SfmOptions, threads: int,
                          seconds: dict, bar, keep_every_feature: bool = False
                          ) -> tuple[int, dict]:
    """SIFT features of ``names`` and their verified matches, into ``database``; returns the
    number of verified (inlier) matches over all pairs, and the features extracted and kept
    (:attr:`SfmResult.features`). With ``options.drop_repeated`` and ``keep_every_feature``
    the features before dropping are kept in :func:`_every_feature_database` of ``database``
    (for :func:`_refine_with_every_feature`)."""
    t = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=_reader_options(camera),
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["features"] = time.perf_counter() - t
    db = pycolmap.Database.open(str(database))
    try:
        features = {"features": int(db.num_keypoints())}
    finally:
        db.close()
    features["kept"] = features["features"]
    if options.drop_repeated > 0:
        bar.set_description("sfm: dropping repeated features")
        t = time.perf_counter()
        if keep_every_feature:
            shutil.copyfile(database, _every_feature_database(database))
        features = drop_repeated_features(database, options.drop_repeated)
        seconds["repeats"] = time.perf_counter() - t
    bar.set_description(f"sfm: {options.matcher} matching")
    t = time.perf_counter()
    matching = _matching_options(options, threads)
    if options.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pycolmap.match_sequential(database, matching_options=matching,
                                  pairing_options=pairing, device=pycolmap.Device.cpu)
    seconds["matching"] = time.perf_counter() - t
    db = pycolmap.Database.open(str(database))
    try:
        return int(db.num_inlier_matches()), features
    finally:
        db.close()


def _every_feature_database(database: Path) -> Path:
    """Where :func:`_features_and_matches` keeps every feature before dropping repeated ones."""
    return database.with_name(database.stem + "_every_feature" + database.suffix)


def _posed_reconstruction(database: Path, cameras, cam_from_world: dict
                          ) -> "pycolmap.Reconstruction":
    """A reconstruction without points of the images of ``database`` named in
    ``cam_from_world`` (name -> pycolmap.Rigid3d), with ``cameras`` (pycolmap cameras)."""
    db = pycolmap.Database.open(str(database))
    try:
        images = db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for cam in cameras:
        rec.add_camera_with_trivial_rig(cam)
    for image in images:
        if image.name in cam_from_world:
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=image.name, camera_id=image.camera_id,
                               image_id=image.image_id), cam_from_world[image.name])
    return rec


def _triangulate(rec: "pycolmap.Reconstruction", database: Path, image_dir: Path, out: Path,
                 threads: int, two_view_tracks: bool) -> "pycolmap.Reconstruction":
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.triangulation.ignore_two_view_tracks = not two_view_tracks
    return pycolmap.triangulate_points(rec, database, image_dir, out, options=mapping)


def _refine_with_every_feature(rec: "pycolmap.Reconstruction", verified: list, database: Path,
                               image_dir: Path, out: Path, options: SfmOptions, threads: int,
                               refine_intrinsics: bool
                               ) -> tuple["pycolmap.Reconstruction", list[int], list[str]]:
    """The second stage of :func:`run_sfm` with ``drop_repeated``: the pairs of posed views
    that the distinct features verified (``verified``) are matched again with every feature
    (``database``, :func:`_every_feature_database`), the points triangulated with ``rec``'s
    poses and cameras, and the whole refined as in the first stage (at least one round). A
    match to the wrong copy of a repeated texture does not triangulate with the right poses;
    the right ones add the points the first stage dropped (on the tabletop at 1024 px: 1346
    points, and a field 1.8 dB behind true poses, without this stage; BENCHMARKS, "Poses from
    images").

    Returns:
        (the refined reconstruction, observations dropped per round, images deregistered).
    """
    out.mkdir(parents=True, exist_ok=True)
    posed = {i: im for i, im in rec.images.items() if im.has_pose}
    pairs = sorted({(posed[a].name, posed[b].name) for a, b, _ in verified
                    if a in posed and b in posed})
    pair_list = out / "pairs.txt"
    pair_list.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_list)
    pycolmap.match_image_pairs(database, matching_options=_matching_options(options, threads),
                               pairing_options=pairing, device=pycolmap.Device.cpu)
    refined = _posed_reconstruction(database, rec.cameras.values(),
                                    {im.name: im.cam_from_world() for im in posed.values()})
    refined = _triangulate(refined, database, image_dir, out, threads, two_view_tracks=False)
    dropped, removed = refine_reconstruction(refined, options.max_reproj_error_px,
                                             max(options.refine_rounds, 1),
                                             refine_intrinsics=refine_intrinsics,
                                             threads=threads)
    return refined, dropped, removed


def _map(database: Path, image_dir: Path, out: Path, seed: int, known_intrinsics: bool,
         threads: int, callback) -> dict:
    """One incremental mapping run into ``out``; returns pycolmap's models (maybe none)."""
    out.mkdir(parents=True, exist_ok=True)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.random_seed = seed
    mapping.ba_refine_focal_length = not known_intrinsics
    mapping.ba_refine_extra_params = not known_intrinsics
    mapping.ba_refine_principal_point = False
    mapping.mapper.abs_pose_refine_focal_length = not known_intrinsics
    mapping.mapper.abs_pose_refine_extra_params = not known_intrinsics
    return pycolmap.incremental_mapping(database, image_dir, out, options=mapping,
                                        next_image_callback=callback)


def verified_matches(database: Path) -> list:
    """Every verified image pair of ``database`` as (image_id_a, image_id_b, (M, 2) inlier
    feature indices)."""
    db = pycolmap.Database.open(str(database))
    try:
        pairs, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    return [(*pycolmap.pair_id_to_image_pair(pair), g.inlier_matches)
            for pair, g in zip(pairs, geometries) if len(g.inlier_matches)]


def explained_matches(rec: "pycolmap.Reconstruction", verified: list) -> int:
    """Verified matches (:func:`verified_matches`) between registered images of ``rec`` whose
    two features observe the same 3D point. A folded model leaves the matches across its fold
    unexplained (on the glassware capture at 1024 px: 0.16 of them explained in a folded run,
    0.28 in a sound one)."""
    point_of = {i: np.array([p.point3D_id if p.has_point3D() else -1 for p in im.points2D],
                            dtype=np.int64)
                for i, im in rec.images.items() if im.has_pose}
    explained = 0
    for a, b, matches in verified:
        if a in point_of and b in point_of:
            pa, pb = point_of[a][matches[:, 0]], point_of[b][matches[:, 1]]
            explained += int(((pa == pb) & (pa >= 0)).sum())
    return explained


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def epipolar_errors_px(a_from_world: np.ndarray, b_from_world: np.ndarray, xa: np.ndarray,
                       xb: np.ndarray, focal_px: float) -> np.ndarray:
    """(M,) Sampson distances, in pixels, of matched points to the epipolar geometry of two
    cameras: ``a_from_world``, ``b_from_world`` (3, 4) world-to-camera [R | t] (COLMAP's
    convention), ``xa``, ``xb`` (M, 2) the matches in normalised image coordinates (lens
    distortion removed), ``focal_px`` the focal length that scales them back to pixels."""
    rot = b_from_world[:, :3] @ a_from_world[:, :3].T
    essential = _skew(b_from_world[:, 3] - rot @ a_from_world[:, 3]) @ rot
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    ea, eb = ha @ essential.T, hb @ essential
    sampson = np.abs(np.sum(hb * ea, 1)) / np.sqrt(
        ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2 + 1e-300)
    return sampson * focal_px


def pose_agreement(rec: "pycolmap.Reconstruction", database: Path,
                   verified: Optional[list] = None,
                   max_error_px: float = AGREEMENT_MAX_ERROR_PX) -> dict:
    """How far the verified matches between registered images agree with the recovered poses.

    A match agrees when its Sampson distance to the epipolar geometry of the two recovered
    poses is under ``max_error_px`` (:func:`epipolar_errors_px`). A pair agrees when most of
    its verified matches do. On a texture that repeats (a tiled or checkered surface),
    matches to the wrong copy of the pattern agree with one another, verification keeps them,
    and views far apart get "verified" pairs with a wrong geometry: few pairs then agree with
    any set of poses, and views may be registered whole periods of the pattern away.

    Args:
        database: COLMAP's database of ``rec`` (the keypoints).
        verified: :func:`verified_matches` of it, when already read.

    Returns:
        {"pairs": verified pairs between registered images, "pairs_agreeing": their share that
        agrees, "matches_agreeing": the share of their verified matches that agrees,
        "max_error_px": the threshold}.
    """
    posed = {i: im for i, im in rec.images.items() if im.has_pose}
    verified = verified_matches(database) if verified is None else verified
    db = pycolmap.Database.open(str(database))
    try:
        normalised = {i: np.asarray(rec.cameras[im.camera_id].cam_from_img(
            db.read_keypoints(i)[:, :2].astype(np.float64)), np.float64)
            for i, im in posed.items()}
    finally:
        db.close()
    agreeing, pairs, matched, right = 0, 0, 0, 0
    for a, b, m in verified:
        if a not in posed or b not in posed:
            continue
        errors = epipolar_errors_px(
            posed[a].cam_from_world().matrix(), posed[b].cam_from_world().matrix(),
            normalised[a][m[:, 0]], normalised[b][m[:, 1]],
            rec.cameras[posed[a].camera_id].mean_focal_length())
        ok = errors < max_error_px
        pairs += 1
        agreeing += int(ok.mean() > 0.5)
        matched += len(m)
        right += int(ok.sum())
    return {"pairs": pairs, "pairs_agreeing": agreeing / max(pairs, 1),
            "matches_agreeing": right / max(matched, 1), "max_error_px": max_error_px}


def _prepare(image_names, work_dir, options) -> tuple[list[str], Path, SfmOptions, int]:
    require_pycolmap()
    options = options or SfmOptions()
    options.check()
    names = list(image_names)
    if len(names) < 2:
        raise ValueError(f"structure from motion needs at least 2 images, got {len(names)}")
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    threads = options.threads if options.threads > 0 else (os.cpu_count() or 1)
    pycolmap.set_random_seed(options.seed)
    return names, work_dir, options, threads


def run_sfm(image_dir: Path, image_names: Sequence[str], work_dir: Path,
            camera: Optional[CameraPrior] = None, options: Optional[SfmOptions] = None,
            progress: bool = True) -> SfmResult:
    """Recover the cameras of ``image_names`` (paths relative to ``image_dir``).

    Args:
        image_dir: folder the names are relative to.
        image_names: the images, in capture order (the sequential matcher relies on it).
        work_dir: an empty or new folder for COLMAP's database and models.
        camera: known shared intrinsics; None estimates one shared SIMPLE_RADIAL camera (focal
            from EXIF when present, else 1.2 x the longer side, then refined).
        options: see :class:`SfmOptions`.
        progress: show a progress bar.

    Raises:
        RuntimeError: wrong pycolmap release.
        ValueError: no model could be built from the images (too few matches).
    """
    names, work_dir, options, threads = _prepare(image_names, work_dir, options)
    database = work_dir / "database.db"
    models_dir = work_dir / "mapper"
    models_dir.mkdir(exist_ok=True)
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    second_stage = options.drop_repeated > 0 and options.refine_all_features
    with quiet_colmap() as console:
        bar = tqdm(total=len(names), desc="sfm: features", unit="image", disable=not progress,
                   file=console)
        inliers, features = _features_and_matches(database, image_dir, names, camera, options,
                                                  threads, seconds, bar,
                                                  keep_every_feature=second_stage)
        t = time.perf_counter()
        known = camera is not None and camera.fixed
        runs, rec, models, best = [], None, {}, -1
        verified = verified_matches(database)
        for run in range(options.mapper_runs):
            bar.set_description(f"sfm: registering (run {run + 1} of {options.mapper_runs})")
            bar.n = 0
            found = _map(database, image_dir, models_dir / str(run), options.seed + run,
                         known, threads, lambda: bar.update(1))
            if not found:
                continue
            largest = max(found.values(), key=lambda r: r.num_reg_images())
            explained = explained_matches(largest, verified)
            runs.append({"seed": options.seed + run, "registered": largest.num_reg_images(),
                         "explained_matches": explained})
            if explained > best:
                rec, models, best = largest, found, explained
        seconds["mapping"] = time.perf_counter() - t
        if rec is None:
            bar.close()
            raise ValueError(
                f"structure from motion found no model for {len(names)} images in {image_dir}: "
                "too few matches (textureless or repetitive content, too little overlap, or "
                "images too small: SIFT needs detail; try larger images or more views)")

        bar.set_description("sfm: refining")
        t = time.perf_counter()
        dropped, removed = refine_reconstruction(
            rec, options.max_reproj_error_px, options.refine_rounds,
            refine_intrinsics=not known, threads=threads)
        seconds["refinement"] = time.perf_counter() - t
        if second_stage:
            bar.set_description("sfm: refining with every feature")
            t = time.perf_counter()
            rec, dropped_again, removed_again = _refine_with_every_feature(
                rec, verified, _every_feature_database(database), image_dir,
                work_dir / "every_feature", options, threads, refine_intrinsics=not known)
            dropped += dropped_again
            removed += removed_again
            seconds["all_features"] = time.perf_counter() - t
        registered = sorted(im.name for im in rec.images.values() if im.has_pose)
        bar.n = len(registered)
        bar.set_description("sfm: done")
        bar.close()
    # the distinct features' matches (image ids are the same in both databases)
    agreement = pose_agreement(rec, database, verified)
    if agreement["pairs_agreeing"] < MIN_PAIRS_AGREEING:
        log.warning(
            "sfm: only %.0f %% of the verified image pairs agree with the recovered poses "
            "(sound models: 60-100 %%): the matches are dominated by a repeated texture, and "
            "some views may be posed whole periods of it away", 100 * agreement["pairs_agreeing"])
    seconds["total"] = time.perf_counter() - start
    log.info("sfm: %d of %d images registered, %d points, %.2f px mean reprojection error; "
             "refinement dropped %s observations and deregistered %s", len(registered),
             len(names), rec.num_points3D(), rec.compute_mean_reprojection_error(), dropped,
             removed or "no image")
    chosen = set(registered)
    return SfmResult(reconstruction=rec, registered=registered,
                     unregistered=[n for n in names if n not in chosen], seconds=seconds,
                     models=len(models), deregistered=removed, inlier_matches=inliers,
                     mapper_runs=runs, agreement=agreement, features=features)


def triangulate_known_poses(image_dir: Path, image_names: Sequence[str], work_dir: Path,
                            camera: CameraPrior, c2w: dict, options: Optional[SfmOptions] = None,
                            progress: bool = True) -> SfmResult:
    """Sparse points of images whose poses are known (a simulator, a robot's kinematics):
    features and matches as :func:`run_sfm`, then triangulation with the poses and intrinsics
    held fixed, and the same outlier filter (points only are re-adjusted).

    Args:
        camera: the images' shared intrinsics (kept fixed).
        c2w: image name -> (4, 4) OpenGL camera-to-world pose, metres.
        options: see :class:`SfmOptions`; None: its defaults, with every feature kept
            (``drop_repeated=0``: the poses cannot be misled by a repeated texture; see
            :attr:`SfmOptions.drop_repeated` for the points it can mislead).
    """
    if options is None:
        options = SfmOptions(drop_repeated=0.0)
    names, work_dir, options, threads = _prepare(image_names, work_dir, options)
    database = work_dir / "database.db"
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    with quiet_colmap() as console:
        bar = tqdm(total=len(names), desc="sfm: features", unit="image", disable=not progress,
                   file=console)
        inliers, features = _features_and_matches(database, image_dir, names, camera, options,
                                                  threads, seconds, bar)
        bar.set_description("sfm: triangulating")
        t = time.perf_counter()
        db = pycolmap.Database.open(str(database))
        try:
            cameras = db.read_all_cameras()
        finally:
            db.close()
        rec = _posed_reconstruction(
            database, cameras,
            {name: pycolmap.Rigid3d(cam_from_world_from_c2w(pose)) for name, pose in c2w.items()})
        # with the poses known, a point two views agree on is as good as a longer track (and
        # two views may be all there is)
        rec = _triangulate(rec, database, image_dir, work_dir / "triangulated", threads,
                           two_view_tracks=True)
        seconds["triangulation"] = time.perf_counter() - t
        t = time.perf_counter()
        dropped, _ = refine_reconstruction(rec, options.max_reproj_error_px,
                                           options.refine_rounds, threads=threads,
                                           fixed_poses=True)
        seconds["refinement"] = time.perf_counter() - t
        bar.n = len(names)
        bar.set_description("sfm: done")
        bar.close()
    seconds["total"] = time.perf_counter() - start
    log.info("sfm: %d points triangulated from %d posed images, %.2f px mean reprojection "
             "error; refinement dropped %s observations", rec.num_points3D(), len(names),
             rec.compute_mean_reprojection_error(), dropped)
    return SfmResult(reconstruction=rec, registered=sorted(names), unregistered=[],
                     seconds=seconds, models=1, inlier_matches=inliers, features=features)
