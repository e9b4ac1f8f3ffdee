"""Place MuJoCo's capture camera at a c2w pose and render RGB, z-depth and geom segmentation.

MuJoCo cameras use the OpenGL axes of the project contract (x right, y up, looking along -z), so a
c2w pose maps directly onto a world-body camera: ``cam_pos`` = translation, ``cam_quat`` = the
rotation as a quaternion. The principal point is the image centre and pixels are square:
``fx = fy = (H / 2) / tan(fovy / 2)``, ``cx = W / 2``, ``cy = H / 2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from nerfbot.data.intrinsics import Intrinsics
from nerfbot.ops.cameras import check_pose, focal_from_fov
from sims.gl import make_renderer
from sims.scene import CAPTURE_CAMERA

#: Largest allowed difference between a requested pose and the one MuJoCo renders with.
POSE_TOL = 1e-6


def intrinsics_from_fovy(fovy_deg: float, width: int, height: int) -> Intrinsics:
    """MuJoCo's projection: vertical fov ``fovy_deg`` over ``height``, square pixels, centred
    principal point (pixel centres at +0.5)."""
    f = focal_from_fov(fovy_deg, height)
    return Intrinsics(f, f, width / 2.0, height / 2.0, int(width), int(height))


@dataclass
class Frame:
    """One rendered view.

    Attributes:
        c2w: (4, 4) float64 pose MuJoCo rendered with (OpenGL convention, metres).
        rgb: (H, W, 3) uint8.
        depth: (H, W) float32 z-depth in metres, ``inf`` where no surface (sky).
        segmentation: (H, W) int32 MuJoCo geom ids, -1 where no geom.
    """

    c2w: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray
    segmentation: np.ndarray


def capture_scene_option() -> mujoco.MjvOption:
    """Visualisation options of a capture: MuJoCo's default geom groups, no sites or decor.

    :mod:`sims.manifest` uses the same geom groups to decide which geoms are content.
    """
    opt = mujoco.MjvOption()
    opt.sitegroup[:] = 0
    return opt


def nearest_rigid(c2w: np.ndarray, where: str = "pose") -> np.ndarray:
    """Validate a c2w pose (``check_pose``) and snap its rotation to the nearest rotation (SVD).

    Returns (4, 4) float64. The snap is below ``check_pose``'s tolerance (1e-4), and makes the
    pose exactly representable by a unit quaternion.
    """
    m = check_pose(c2w, where).copy()
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ vt
    return m


def pose_to_mujoco(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pos (3,), quat (4,) w-x-y-z) of a world-body camera with pose ``c2w`` (4, 4)."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(c2w[:3, :3]).reshape(-1))
    return np.array(c2w[:3, 3], dtype=np.float64), quat


class CaptureCamera:
    """Renders a compiled model from arbitrary c2w poses through the :data:`CAPTURE_CAMERA`.

    Args:
        model, data: from :func:`sims.scene.load_capture_model` (``mj_forward`` already run).
        width, height: image size in pixels.
        fovy_deg: vertical field of view in degrees.

    Use as a context manager (or call :meth:`close`) to release the GL context.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, width: int, height: int,
                 fovy_deg: float):
        self.model, self.data = model, data
        self.cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, CAPTURE_CAMERA)
        if self.cam_id < 0:
            raise ValueError(f"model has no camera '{CAPTURE_CAMERA}'; "
                             "load it with sims.scene.load_capture_model")
        self.intrinsics = intrinsics_from_fovy(fovy_deg, width, height)
        model.cam_fovy[self.cam_id] = fovy_deg
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), int(width))
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), int(height))
        self.option = capture_scene_option()
        self._renderer = make_renderer(model, int(height), int(width))
        extent = float(model.stat.extent)
        self.far = float(model.vis.map.zfar) * extent

    def place(self, c2w: np.ndarray, where: str = "pose") -> np.ndarray:
        """Move the camera to ``c2w`` and return the pose MuJoCo computed, (4, 4) float64.

        Raises:
            ValueError: the pose is invalid (see ``check_pose``), or MuJoCo's camera frame
                differs from the request by more than :data:`POSE_TOL`.
        """
        want = nearest_rigid(c2w, where)
        pos, quat = pose_to_mujoco(want)
        self.model.cam_pos[self.cam_id] = pos
        self.model.cam_quat[self.cam_id] = quat
        mujoco.mj_camlight(self.model, self.data)
        got = self.rendered_pose()
        err = float(np.abs(got - want).max())
        if not err <= POSE_TOL:
            raise ValueError(f"{where}: MuJoCo placed the camera {err:.2e} away from the "
                             f"requested pose (tolerance {POSE_TOL})")
        return got

    def rendered_pose(self) -> np.ndarray:
        """Current c2w (4, 4) of the capture camera from ``data.cam_xpos/cam_xmat``."""
        c2w = np.eye(4)
        c2w[:3, :3] = self.data.cam_xmat[self.cam_id].reshape(3, 3)
        c2w[:3, 3] = self.data.cam_xpos[self.cam_id]
        return c2w

    def render(self, c2w: np.ndarray, where: str = "pose") -> Frame:
        """Place the camera at ``c2w`` and render one :class:`Frame`."""
        pose = self.place(c2w, where)
        r = self._renderer
        r.update_scene(self.data, camera=self.cam_id, scene_option=self.option)
        rgb = r.render().copy()
        r.enable_depth_rendering()
        depth = r.render().astype(np.float32, copy=True)
        r.enable_segmentation_rendering()
        seg_raw = r.render().copy()
        r.disable_segmentation_rendering()

        nothing = seg_raw[..., 0] < 0
        sky = nothing | (depth >= np.float32(self.far) * np.float32(1.0 - 1e-5))
        depth[sky] = np.inf
        is_geom = seg_raw[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        seg = np.where(is_geom & ~sky, seg_raw[..., 0], -1).astype(np.int32)
        return Frame(pose, rgb, depth, seg)

    def depth_without(self, geom_ids, hidden_group: int = 5) -> np.ndarray:
        """z-depth (H, W) float32, metres (``inf`` = nothing) of the current view with the geoms
        ``geom_ids`` hidden: what lies behind them. Call after :meth:`render` or :meth:`place`.

        The geoms are moved to ``hidden_group`` (a geom group the capture options never draw)
        for this one render and restored afterwards.
        """
        ids = np.asarray(list(geom_ids), dtype=np.int64)
        saved = self.model.geom_group[ids].copy()
        option = capture_scene_option()
        option.geomgroup[hidden_group] = 0
        r = self._renderer
        try:
            self.model.geom_group[ids] = hidden_group
            r.update_scene(self.data, camera=self.cam_id, scene_option=option)
            r.enable_depth_rendering()
            depth = r.render().astype(np.float32, copy=True)
        finally:
            r.disable_depth_rendering()
            self.model.geom_group[ids] = saved
        depth[depth >= np.float32(self.far) * np.float32(1.0 - 1e-5)] = np.inf
        return depth

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> "CaptureCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
