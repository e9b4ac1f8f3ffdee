"""Depth queries (expected / median / threshold), point clouds and the depth-mode sweep, on an
analytic field (a slab of known density) rendered through the real occupancy-grid renderer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.eval.depth_eval import best_threshold
from nerfbot.fields.background import FixedBackground
from nerfbot.fields.base import Field
from nerfbot.models.occupancy import OccupancyModel
from nerfbot.ops.cameras import Cameras, look_at
from nerfbot.ops.pointcloud import cloud_arrays, depth_to_cloud, fuse_clouds
from nerfbot.query.render import depth, render_image

SLAB_DENSITY = 40.0      # 1/m: faint, like glass (opacity 1 - exp(-40 * 0.02) = 0.55)
SLAB = (0.50, 0.52)      # z range of the slab, metres
FLOOR_Z = 0.2            # an opaque floor below it (density 1e4 for z < FLOOR_Z)


class SlabField(Field):
    """sigma = SLAB_DENSITY inside SLAB, 1e4 below FLOOR_Z, 0 elsewhere; constant grey."""

    def density(self, x, cond=None):
        z = x[:, 2]
        sigma = torch.where((z >= SLAB[0]) & (z <= SLAB[1]), SLAB_DENSITY, 0.0)
        sigma = torch.where(z < FLOOR_Z, 1e4, sigma)
        return sigma.to(x.dtype), torch.zeros(len(x), 1)

    def color(self, feat, d, cond=None):
        return torch.full((len(feat), 3), 0.5)


@pytest.fixture(scope="module")
def slab_model():
    aabb = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    model = OccupancyModel(SlabField(), FixedBackground((1.0, 1.0, 1.0)), aabb)
    return model.eval()


def _down_camera(height=1.5, size=16):
    c2w = look_at(np.array([0.0, 0.0, height]), np.array([0.0, 0.0, 0.0]), up=np.array([0, 1.0, 0]))
    f = size / (2 * np.tan(np.radians(20) / 2))
    return Cameras.from_numpy(c2w[None], [[f, f, size / 2, size / 2]], [[size, size]]), c2w


def test_threshold_depth_finds_the_faint_slab_that_expected_depth_misses(slab_model):
    cams, _ = _down_camera()
    z_threshold = depth(slab_model, cams, 0, mode="threshold", threshold=10.0)
    z_expected = depth(slab_model, cams, 0, mode="expected")
    z_median = depth(slab_model, cams, 0, mode="median")
    surface = 1.5 - SLAB[1]                                  # z-depth of the slab's top face
    step = float(slab_model.dt_min)
    # first crossing, interpolated between samples: within one marching step of the face
    assert np.abs(z_threshold - surface).max() < step
    # expected depth lies between the slab and the floor (weight split 55 / 45)
    assert np.all(z_expected > surface + 0.1) and np.all(z_expected < 1.5 - FLOOR_Z)
    # median depth jumps between the two surfaces (the slab holds about half the weight): it
    # is never the blend that expected depth is
    near_slab = np.abs(z_median - surface) < 0.03
    near_floor = np.abs(z_median - (1.5 - FLOOR_Z)) < 0.03
    assert np.all(near_slab | near_floor)


def test_threshold_above_every_density_is_invalid_not_the_near_plane(slab_model):
    cams, _ = _down_camera()
    maps = depth(slab_model, cams, 0, mode="threshold", threshold=[10.0, 1e3, 1e5])
    assert maps.shape == (3, 16, 16)
    surface = 1.5 - SLAB[1]
    assert np.abs(maps[0] - surface).max() < float(slab_model.dt_min)
    assert np.abs(maps[1] - (1.5 - FLOOR_Z)).max() < float(slab_model.dt_min)  # slab too faint
    assert np.isnan(maps[2]).all()                                            # never reached


def test_depth_query_rejects_bad_modes_and_thresholds(slab_model):
    cams, _ = _down_camera()
    with pytest.raises(ValueError, match="unknown depth mode"):
        depth(slab_model, cams, 0, mode="mean")
    with pytest.raises(ValueError, match="needs threshold"):
        depth(slab_model, cams, 0, mode="threshold")
    with pytest.raises(ValueError, match="finite and > 0"):
        depth(slab_model, cams, 0, mode="threshold", threshold=-1.0)


def test_ray_distance_and_z_depth_differ_by_the_ray_cosine(slab_model):
    cams, _ = _down_camera()
    img = render_image(slab_model, cams, 0, thresholds=[10.0])
    rays = cams.rays(0)
    cos = rays.z_per_t.numpy().reshape(16, 16)
    np.testing.assert_allclose(img["threshold_z_depth"][0], img["threshold_depth"][0] * cos,
                               rtol=1e-5)


def test_depth_map_back_projects_onto_the_plane_with_normals_towards_the_camera(slab_model):
    cams, c2w = _down_camera(size=24)
    z = depth(slab_model, cams, 0, mode="threshold", threshold=10.0)
    fx, fy, cx, cy = (float(v) for v in (cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0]))
    cloud = depth_to_cloud(z, fx, fy, cx, cy, c2w, normal_radius=0.05)
    pts, normals = cloud_arrays(cloud)
    assert len(pts) == 24 * 24
    # every pixel lands on the slab's top face (world z = 0.52) within a marching step
    assert np.abs(pts[:, 2] - SLAB[1]).max() < float(slab_model.dt_min)
    assert np.all(normals[:, 2] > 0.95) and np.median(normals[:, 2]) > 0.99  # up, to the camera
    # NaN pixels are skipped, and fusing keeps normals
    z[:5] = np.nan
    part = depth_to_cloud(z, fx, fy, cx, cy, c2w, normal_radius=0.05)
    assert len(part.points) == 24 * 19
    both = fuse_clouds([cloud, part])
    assert len(both.points) == 24 * 43 and both.has_normals()


def test_depth_to_cloud_matches_pinhole_back_projection_with_pixel_centres():
    rng = np.random.default_rng(0)
    h, w = 6, 8
    z = rng.uniform(0.5, 2.0, size=(h, w)).astype(np.float32)
    fx, fy, cx, cy = 7.0, 6.5, 4.0, 3.0
    c2w = look_at(np.array([0.3, -1.0, 0.8]), np.array([0.0, 0.0, 0.2]))
    pts, _ = cloud_arrays(depth_to_cloud(z, fx, fy, cx, cy, c2w, normals=False))
    v, u = np.mgrid[0:h, 0:w]
    cam = np.stack([(u + 0.5 - cx) / fx * z, -(v + 0.5 - cy) / fy * z, -z], -1).reshape(-1, 3)
    want = cam @ c2w[:3, :3].T + c2w[:3, 3]
    np.testing.assert_allclose(pts, want, atol=1e-5)


def test_best_threshold_needs_enough_valid_pixels():
    rows = [dict(threshold=1.0, mae_m=0.05, valid_fraction=1.0),
            dict(threshold=10.0, mae_m=0.01, valid_fraction=0.95),
            dict(threshold=100.0, mae_m=0.001, valid_fraction=0.3),
            dict(threshold=1000.0, mae_m=None, valid_fraction=0.0)]
    assert best_threshold(rows) == 10.0
    assert best_threshold(rows, min_valid=0.2) == 100.0
    assert best_threshold(rows[3:]) is None


def test_pooled_sweeps_weight_by_pixels_with_a_prediction():
    from nerfbot.eval.depth_eval import DepthSweep, pool_sweeps

    def sweep(mae, valid, pixels, n_images):
        row = dict(mae_m=mae, rmse_m=2 * mae, valid_fraction=valid, pixels=pixels)
        s = DepthSweep([10.0], num_images=n_images)
        for c in ("transparent", "opaque_objects", "scene"):
            s.modes[c] = {"expected": dict(row)}
            s.threshold[c] = [dict(threshold=10.0, **row)]
        return s

    pooled = pool_sweeps([sweep(0.01, 1.0, 100, 2), sweep(0.04, 0.5, 200, 3)])
    row = pooled.threshold["transparent"][0]
    # 100 predicted pixels at 1 cm and 100 at 4 cm; 200 of 300 pixels have a depth
    assert row["mae_m"] == pytest.approx(0.025)
    assert row["rmse_m"] == pytest.approx(np.sqrt((100 * 0.02 ** 2 + 100 * 0.08 ** 2) / 200))
    assert row["valid_fraction"] == pytest.approx(2 / 3) and row["pixels"] == 300
    assert pooled.num_images == 5
    assert pooled.best_threshold["transparent"] is None       # 67 % < the 80 % required
    with pytest.raises(ValueError, match="share their thresholds"):
        pool_sweeps([sweep(0.01, 1, 1, 1), DepthSweep([5.0])])


class StripedSlabField(SlabField):
    """The slab field with colour stripes 3 cm wide along x: pixels see several stripes."""

    def density(self, x, cond=None):
        sigma, _ = super().density(x, cond)
        return sigma, x[:, :1]

    def color(self, feat, d, cond=None):
        stripe = (torch.floor(feat[:, 0] / 0.03) % 2).float()
        return torch.stack([stripe, 1 - stripe, torch.full_like(stripe, 0.5)], -1)


def test_supersampled_render_averages_colour_over_the_pixel_and_keeps_centre_depth():
    """render_image(supersample=S): rgb and opacity are the S x S cell-centre rays' means (the
    area average of a render at S times the resolution); the depths are the centre ray's;
    None takes the model's own setting."""
    from nerfbot.models.occupancy import OccupancyModelConfig

    aabb = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    model = OccupancyModel(StripedSlabField(), FixedBackground((1.0, 1.0, 1.0)), aabb,
                           OccupancyModelConfig(supersample=2, supersample_pattern="grid")).eval()
    cams, _ = _down_camera(size=12)
    centre = render_image(model, cams, 0, supersample=1)
    fine = render_image(model, cams.scaled(2), 0, supersample=1)
    for s in (None, 2):
        img = render_image(model, cams, 0, supersample=s)
        np.testing.assert_allclose(img["rgb"], fine["rgb"].reshape(12, 2, 12, 2, 3).mean((1, 3)),
                                   atol=1e-6)
        np.testing.assert_allclose(img["opacity"], fine["opacity"].reshape(12, 2, 12, 2).mean((1, 3)),
                                   atol=1e-6)
        for k in ("z_depth", "depth", "median_z_depth"):
            np.testing.assert_array_equal(img[k], centre[k])
    # stripes 3 cm wide, pixels ~4 cm wide on the slab: averaging changes the colours
    assert np.abs(img["rgb"] - centre["rgb"]).max() > 0.2
    # depth queries do not pay for the colour rays: the same map either way
    np.testing.assert_array_equal(depth(model, cams, 0), centre["z_depth"])


def test_corner_pattern_weighs_the_centre_and_the_shared_corner_rays():
    """supersample_pattern="corners": rgb and opacity are 2/3 x the centre ray's plus 1/12 x
    each of the pixel's four corner rays; the corner rays are the pixel-centre rays of the
    same camera shifted by half a pixel and one pixel larger; depths are the centre ray's.
    On stripes finer than a pixel it stays closer to the area average than the centre ray."""
    from nerfbot.models.occupancy import OccupancyModelConfig
    from nerfbot.query.render import render_rays_chunked

    aabb = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    model = OccupancyModel(StripedSlabField(), FixedBackground((1.0, 1.0, 1.0)), aabb,
                           OccupancyModelConfig(supersample=2,
                                                supersample_pattern="corners")).eval()
    cams, c2w = _down_camera(size=12)
    f = float(cams.fx[0])
    shifted = Cameras.from_numpy(c2w[None], [[f, f, 6.5, 6.5]], [[13, 13]])
    corners, centres = cams.corner_rays(0), shifted.rays(0)
    torch.testing.assert_close(corners.directions, centres.directions)
    torch.testing.assert_close(corners.z_per_t, centres.z_per_t)
    centre = render_image(model, cams, 0, supersample=1)
    at_corners = render_rays_chunked(model, corners)
    c_rgb = at_corners["rgb"].reshape(13, 13, 3).numpy()
    c_op = at_corners["opacity"].reshape(13, 13).numpy()
    quad = (lambda a: (a[:-1, :-1] + a[:-1, 1:] + a[1:, :-1] + a[1:, 1:]) / 12.0)
    for img in (render_image(model, cams, 0),
                render_image(model, cams, 0, supersample_pattern="corners")):
        np.testing.assert_allclose(img["rgb"], 2 / 3 * centre["rgb"] + quad(c_rgb), atol=1e-6)
        np.testing.assert_allclose(img["opacity"], 2 / 3 * centre["opacity"] + quad(c_op),
                                   atol=1e-6)
        for k in ("z_depth", "depth", "median_z_depth"):
            np.testing.assert_array_equal(img[k], centre[k])
    area = render_image(model, cams.scaled(8), 0, supersample=1)["rgb"]
    area = area.reshape(12, 8, 12, 8, 3).mean((1, 3))
    error = (lambda a: np.abs(a - area).mean())
    assert error(img["rgb"]) < 0.6 * error(centre["rgb"])
    grid = render_image(model, cams, 0, supersample_pattern="grid")
    np.testing.assert_array_equal(grid["rgb"], render_image(model, cams, 0, supersample=2,
                                  supersample_pattern="grid")["rgb"])
    with pytest.raises(ValueError, match="supersample_pattern"):
        render_image(model, cams, 0, supersample_pattern="diagonal")
    with pytest.raises(ValueError, match="supersample_pattern"):
        OccupancyModelConfig(supersample_pattern="diagonal")


class WideStripedSlabField(StripedSlabField):
    """Stripes 20 cm wide: uniform regions a few pixels across, edges between them."""

    def color(self, feat, d, cond=None):
        stripe = (torch.floor(feat[:, 0] / 0.2) % 2).float()
        return torch.stack([stripe, 1 - stripe, torch.full_like(stripe, 0.5)], -1)


def test_supersample_tolerance_casts_extra_rays_only_at_edges():
    """With a tolerance, pixels whose 3 x 3 centre colours span more than it get the S x S
    mean; the others keep their centre ray. 0 is the full supersampled render; the model's
    option is the default."""
    from nerfbot.models.occupancy import OccupancyModelConfig
    from nerfbot.query.render import edge_pixels

    aabb = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    model = OccupancyModel(WideStripedSlabField(), FixedBackground((1.0, 1.0, 1.0)), aabb,
                           OccupancyModelConfig(supersample=2, supersample_tolerance=0.1,
                                                supersample_pattern="grid")).eval()
    cams, _ = _down_camera(size=24)
    centre = render_image(model, cams, 0, supersample=1)
    full = render_image(model, cams, 0, supersample=2, supersample_tolerance=0.0)
    picked = np.zeros(24 * 24, bool)
    picked[edge_pixels(centre["rgb"], 0.1)] = True
    assert 0.05 < picked.mean() < 0.6           # the stripes' edges, not the whole image
    for img in (render_image(model, cams, 0), render_image(model, cams, 0,
                                                              supersample_tolerance=0.1)):
        rgb, ref, c = (a.reshape(-1, 3) for a in (img["rgb"], full["rgb"], centre["rgb"]))
        np.testing.assert_allclose(rgb[picked], ref[picked], atol=1e-6)
        np.testing.assert_array_equal(rgb[~picked], c[~picked])
        np.testing.assert_allclose(rgb, ref, atol=0.1)   # off only where nothing changes
    # a tolerance above any colour difference: the centre render inside the border
    inner = render_image(model, cams, 0, supersample_tolerance=2.0)["rgb"][1:-1, 1:-1]
    np.testing.assert_array_equal(inner, centre["rgb"][1:-1, 1:-1])
    # a uniform image: only the border, whose outside is unknown
    assert edge_pixels(np.zeros((4, 4, 3)), 0.0).tolist() == [0, 1, 2, 3, 4, 7, 8, 11, 12, 13,
                                                              14, 15]


def test_adaptive_pattern_takes_the_grid_where_centre_and_corners_disagree():
    """"adaptive": pixels whose centre and four corner colours span more than the tolerance
    get the S x S grid's mean (the grid render's colour there), the others keep the corner
    rule (the "corners" render's colour); the depths stay the centre ray's. It is the default
    pattern of the occupancy renderer."""
    from nerfbot.models.occupancy import OccupancyModelConfig
    from nerfbot.query.render import render_rays_chunked

    assert OccupancyModelConfig().supersample_pattern == "adaptive"
    aabb = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    model = OccupancyModel(WideStripedSlabField(), FixedBackground((1.0, 1.0, 1.0)), aabb,
                           OccupancyModelConfig(supersample=2, adaptive_tolerance=0.1)).eval()
    cams, _ = _down_camera(size=24)
    centre = render_image(model, cams, 0, supersample=1)
    corner_rule = render_image(model, cams, 0, supersample_pattern="corners")
    grid = render_image(model, cams, 0, supersample_pattern="grid")
    c = render_rays_chunked(model, cams.corner_rays(0))["rgb"].reshape(25, 25, 3).numpy()
    five = np.stack([centre["rgb"], c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
    picked = (five.max(0) - five.min(0)).max(-1).reshape(-1) > 0.1
    assert 0.05 < picked.mean() < 0.6           # the stripes' edges, not the whole image
    img = render_image(model, cams, 0)          # the model's pattern and tolerance
    rgb, g, r = (a.reshape(-1, 3) for a in (img["rgb"], grid["rgb"], corner_rule["rgb"]))
    np.testing.assert_allclose(rgb[picked], g[picked], atol=1e-6)
    np.testing.assert_allclose(rgb[~picked], r[~picked], atol=1e-6)
    assert np.abs(rgb - r).max() > 0.05         # the grid does differ at the edges
    for k in ("z_depth", "depth", "median_z_depth"):
        np.testing.assert_array_equal(img[k], centre[k])
    # a tolerance above any colour difference is the corner rule everywhere, 0 nearly the grid
    np.testing.assert_allclose(render_image(model, cams, 0, adaptive_tolerance=2.0)["rgb"],
                               corner_rule["rgb"], atol=1e-6)
    with pytest.raises(ValueError, match="adaptive_tolerance"):
        OccupancyModelConfig(adaptive_tolerance=-0.1)
