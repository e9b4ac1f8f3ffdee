"""``nerfbot view``: a trained run in the browser, through viser.

The field is rendered at each browser's camera: a preview (``preview_divisor`` times fewer
pixels per side, one ray per pixel) while the camera moves, then the full resolution (the run's
rays per pixel) once it has been still for ``still_seconds``. Frames are rendered on one
background thread, newest camera first; a camera that moves again before its frame is done
simply gets the next frame.

Conventions: viser reports camera poses in the OpenCV convention (+z forward, +y down); the
project's poses are OpenGL (``-z`` forward, ``+y`` up), so ``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``.
The scene's up direction is +z (MuJoCo's).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import trimesh
import viser
from scipy.spatial.transform import Rotation

from nerfbot.data.conditioning import Conditioning
from nerfbot.data.writers import write_json_atomic
from nerfbot.models.base import Model
from nerfbot.ops.cameras import Cameras
from nerfbot.query.export import colorize_depth, colorize_labels, to_uint8
from nerfbot.query.render import DEPTH_MODES, depth_of, render_image
from sims.rigs import read_pose_file

log = logging.getLogger(__name__)

#: OpenCV camera axes -> OpenGL camera axes (and back: it is its own inverse).
CV_TO_GL = np.diag([1.0, -1.0, -1.0])
#: What the viewer can show; "labels" only for runs with a label head.
SHOW = ("rgb", "depth", "opacity", "labels")
#: At most this many training cameras are drawn as frustums (evenly picked).
MAX_FRUSTUMS = 300


def c2w_from_viser(wxyz: Sequence[float], position: Sequence[float]) -> np.ndarray:
    """(4, 4) float64 camera-to-world pose, OpenGL convention, from a viser camera's
    orientation quaternion (w, x, y, z; OpenCV camera axes) and position (metres)."""
    w, x, y, z = (float(v) for v in wxyz)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix() @ CV_TO_GL
    pose[:3, 3] = np.asarray(position, dtype=np.float64)
    return pose


def viser_from_c2w(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz (4,), position (3,)) of a viser camera or frustum at OpenGL pose ``c2w`` (4, 4)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    x, y, z, w = Rotation.from_matrix(c2w[:3, :3] @ CV_TO_GL).as_quat()
    return np.array([w, x, y, z]), c2w[:3, 3].copy()


def look_at_pose(eye: Sequence[float], target: Sequence[float], up: Sequence[float]) -> np.ndarray:
    """(4, 4) OpenGL c2w of a camera at ``eye`` looking at ``target`` with ``up`` up (no roll),
    as viser's orbit camera places it."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(back, right), back, eye
    return pose


@dataclass
class StartView:
    """Where a browser's camera starts: eye, look-at target and up (world metres) and the
    vertical field of view (degrees)."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_deg: float

    @staticmethod
    def of_camera(c2w: np.ndarray, fov_deg: float, distance: float) -> "StartView":
        """The view of an OpenGL camera ``c2w`` (4, 4), looking at the point ``distance``
        metres ahead of it (the orbit's centre), with the scene's up (+z) as the orbit's up
        (the camera's own up when it looks straight up or down). A camera without roll is
        reproduced exactly."""
        c2w = np.asarray(c2w, dtype=np.float64)
        eye, back = c2w[:3, 3], c2w[:3, 2]
        up = np.array([0.0, 0.0, 1.0])
        if np.linalg.norm(np.cross(up, back)) < 1e-3:
            up = c2w[:3, 1].copy()
        return StartView(eye, eye - distance * back, up, float(fov_deg))

    def pose(self) -> np.ndarray:
        return look_at_pose(self.eye, self.target, self.up)


@dataclass
class Settings:
    """What is rendered: ``show`` (one of :data:`SHOW`), the depth query, the condition vector
    (time or joints; None for static runs) and the full-resolution image height (pixels)."""

    show: str = "rgb"
    depth_mode: str = "expected"
    threshold: float = 100.0
    condition: Optional[list] = None
    height: int = 128
    version: int = 0


@dataclass
class FrameStat:
    """One frame sent to a browser: ``kind`` "preview" or "full", its size (pixels), the render
    time and the time since its camera (or settings) changed (seconds)."""

    client: int
    kind: str
    width: int
    height: int
    render_s: float
    since_change_s: float
    sent_at: float


@dataclass
class _ClientState:
    camera_version: int = 0
    changed_at: float = field(default_factory=time.perf_counter)
    rendered: tuple = (-1, -1)  # (camera version, settings version) of the last frame sent
    rendered_full: bool = False


class CameraPathFile:
    """Keyframes saved from the viewer, in the pose-file format ``nerfbot render --poses`` and
    ``capture --poses`` read: ``{"poses": [{"transform_matrix": 4x4}, ...]}``. An existing file
    is read first (it must be such a flat list) and extended, never replaced by something else;
    every save is written atomically."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.poses: list[np.ndarray] = []
        if self.path.exists():
            poses = read_pose_file(self.path)
            if isinstance(poses, dict):
                raise ValueError(f"{self.path}: a camera path is one list of poses, not "
                                 f"per-split lists {sorted(poses)}")
            self.poses = list(poses)

    def append(self, c2w: np.ndarray) -> int:
        """Add a keyframe (OpenGL c2w (4, 4)); returns the number of keyframes."""
        self.poses.append(np.asarray(c2w, dtype=np.float64))
        write_json_atomic(self.path, {"poses": [{"transform_matrix": p.tolist()}
                                                for p in self.poses]})
        return len(self.poses)


def load_geometry(path: Path) -> trimesh.Trimesh | trimesh.PointCloud:
    """A mesh or point cloud file (.ply, .obj, .glb, ...) as one trimesh object; ValueError
    naming the file when it is unreadable or empty."""
    try:
        loaded = trimesh.load(str(path))
    except Exception as err:  # trimesh raises many kinds for a bad file
        raise ValueError(f"{path}: cannot read geometry: {err}") from None
    if isinstance(loaded, trimesh.Scene):
        parts = list(loaded.dump()) if loaded.geometry else []
        meshes = [g for g in parts if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(meshes) if meshes else (parts[0] if parts else None)
    if loaded is None or not len(getattr(loaded, "vertices", [])):
        raise ValueError(f"{path}: no vertices: nothing to show")
    return loaded


class Viewer:
    """A viser server that renders ``model`` at every connected browser's camera.

    Args:
        model: a trained model (eval mode).
        conditioning: the run's conditioning (time or joint sliders for conditioned runs).
        train_cameras: the training cameras, drawn as frustums (None: none drawn).
        start: where browsers' cameras start.
        settings: the initial :class:`Settings`.
        path_file: where "save camera" appends keyframes (:class:`CameraPathFile`).
        geometry: mesh / point-cloud files to show beside the field.
        title: shown at the top of the control panel.
        host, port: where the server listens (port 0: a free port).
    """

    def __init__(self, model: Model, conditioning: Conditioning, *,
                 train_cameras: Optional[Cameras], start: StartView, settings: Settings,
                 path_file: Path, geometry: Sequence[Path] = (), title: str = "nerfbot",
                 host: str = "127.0.0.1", port: int = 8080, preview_divisor: int = 4,
                 still_seconds: float = 0.3):
        self.model = model
        self.conditioning = conditioning
        self.settings = settings
        self.start_view = start
        self.preview_divisor = max(int(preview_divisor), 1)
        self.still_seconds = float(still_seconds)
        self.path_file = CameraPathFile(path_file)
        self.geometry = [(Path(p), load_geometry(Path(p))) for p in geometry]
        self.stats: list[FrameStat] = []
        self.connected_at: dict[int, float] = {}
        self._clients: dict[int, _ClientState] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        cam = self.server.initial_camera
        cam.position, cam.look_at = tuple(start.eye), tuple(start.target)
        cam.up = tuple(start.up)
        cam.fov = float(np.radians(start.fov_deg))
        extent = float(np.linalg.norm(np.ptp(model.aabb.detach().cpu().numpy(), axis=0)))
        self._add_scene(train_cameras, extent)
        self._add_gui(title)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._render_loop, name="nerfbot-view",
                                        daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ scene and controls

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    def _add_scene(self, cams: Optional[Cameras], extent: float) -> None:
        aabb = self.model.aabb.detach().cpu().numpy().astype(np.float64)
        self.bounds = self.server.scene.add_box(
            "/bounds", color=(255, 160, 0), dimensions=tuple(aabb[1] - aabb[0]), wireframe=True,
            position=tuple(0.5 * (aabb[0] + aabb[1])))
        self.frustums = []
        if cams is not None and len(cams):
            pick = np.unique(np.linspace(0, len(cams) - 1, min(len(cams), MAX_FRUSTUMS))
                             .round().astype(int))
            for i in pick:
                h, w = int(cams.height[i]), int(cams.width[i])
                fov = 2.0 * float(np.arctan(0.5 * h / float(cams.fy[i])))
                wxyz, pos = viser_from_c2w(cams.c2w[i].cpu().numpy())
                self.frustums.append(self.server.scene.add_camera_frustum(
                    f"/train_cameras/{i}", fov=fov, aspect=w / h, scale=0.03 * extent,
                    thickness=0.002 * extent, color=(40, 90, 220), wxyz=wxyz, position=pos))
        for k, (path, geom) in enumerate(self.geometry):
            name = f"/geometry/{k}_{path.stem}"
            if isinstance(geom, trimesh.PointCloud):
                colors = np.asarray(geom.colors)[:, :3] if len(geom.colors) else (180, 180, 180)
                self.server.scene.add_point_cloud(name, np.asarray(geom.vertices, np.float32),
                                                  colors, point_size=0.004 * extent)
            else:
                self.server.scene.add_mesh_trimesh(name, geom)

    def _add_gui(self, title: str) -> None:
        gui, s = self.server.gui, self.settings
        gui.configure_theme(control_width="medium", show_share_button=False)
        gui.add_markdown(f"**{title}**")
        shows = [v for v in SHOW if v != "labels" or self.model.label_head is not None]
        self.gui_show = gui.add_dropdown("show", shows, initial_value=s.show)
        self.gui_depth = gui.add_dropdown("depth mode", DEPTH_MODES, initial_value=s.depth_mode,
                                          hint="expected, median, or threshold (Dex-NeRF, glass)")
        self.gui_threshold = gui.add_number("threshold (1/m)", float(s.threshold), min=1e-3,
                                            step=1.0, hint="density of threshold depth")
        self.gui_height = gui.add_slider("resolution (px)", 32, max(1024, int(s.height)), 16,
                                         int(s.height),
                                         hint="height of a still frame, in pixels")
        self.gui_conditions = []
        for name, (lo, hi) in zip(self.conditioning.names, self.conditioning.ranges):
            value = s.condition[len(self.gui_conditions)] if s.condition else 0.5 * (lo + hi)
            self.gui_conditions.append(gui.add_slider(name, float(lo), float(hi),
                                                      (hi - lo) / 200.0, float(value)))
        self.gui_frustums = gui.add_checkbox("training cameras", bool(self.frustums))
        self.gui_bounds = gui.add_checkbox("scene bounds", True)
        self.gui_save = gui.add_button("save camera", hint=f"append this view to "
                                                           f"{self.path_file.path}")
        self.gui_status = gui.add_markdown("waiting for a browser")
        for handle in (self.gui_show, self.gui_depth, self.gui_threshold, self.gui_height,
                       *self.gui_conditions):
            handle.on_update(lambda _: self._settings_changed())
        self.gui_frustums.on_update(lambda _: self._toggle(self.frustums, self.gui_frustums))
        self.gui_bounds.on_update(lambda _: self._toggle([self.bounds], self.gui_bounds))
        self.gui_save.on_click(self._save_camera)

    @staticmethod
    def _toggle(handles, box) -> None:
        for h in handles:
            h.visible = bool(box.value)

    def _settings_changed(self) -> None:
        with self._lock:
            s = self.settings
            s.show, s.depth_mode = self.gui_show.value, self.gui_depth.value
            s.threshold = max(float(self.gui_threshold.value), 1e-3)
            s.height = int(self.gui_height.value)
            if self.gui_conditions:
                s.condition = [float(g.value) for g in self.gui_conditions]
            s.version += 1
        self._wake.set()

    def _save_camera(self, event) -> None:
        cam = event.client.camera
        n = self.path_file.append(c2w_from_viser(cam.wxyz, cam.position))
        event.client.add_notification(
            "camera saved", f"keyframe {n} in {self.path_file.path}; render the path with "
            f"`nerfbot render RUN --poses {self.path_file.path} --out path.mp4`",
            auto_close_seconds=6.0)

    # ------------------------------------------------------------------ clients

    def _on_connect(self, client) -> None:
        with self._lock:
            self._clients[client.client_id] = _ClientState()
            self.connected_at[client.client_id] = time.perf_counter()

        def moved(_camera) -> None:
            with self._lock:
                state = self._clients.get(client.client_id)
                if state is not None:
                    state.camera_version += 1
                    state.changed_at = time.perf_counter()
            self._wake.set()

        client.camera.on_update(moved)
        self._wake.set()

    def _on_disconnect(self, client) -> None:
        with self._lock:
            self._clients.pop(client.client_id, None)

    def _next_job(self):
        """(client, state, key, full) of the frame to render next, or None: a camera or the
        settings changed since the client's last frame (a preview while it keeps changing, the
        full frame once still), or a still camera whose last frame was a preview."""
        now, best = time.perf_counter(), None
        with self._lock:
            clients = {c.client_id: c for c in self.server.get_clients().values()}
            for cid, state in self._clients.items():
                client = clients.get(cid)
                if client is None or state.camera_version == 0:
                    continue  # no camera reported yet
                key = (state.camera_version, self.settings.version)
                still = now - state.changed_at >= self.still_seconds
                if key != state.rendered or (still and not state.rendered_full):
                    if best is None or state.changed_at < best[1].changed_at:
                        best = (client, state, key, still)
        return best

    # ------------------------------------------------------------------ rendering

    def render_view(self, c2w: np.ndarray, fov_deg: float, width: int, height: int,
                    settings: Settings, full: bool) -> tuple[np.ndarray, np.ndarray]:
        """(image (H, W, 3) uint8, z-depth (H, W) metres with +inf where nothing is hit) of the
        field at OpenGL pose ``c2w`` (4, 4), as the viewer shows it."""
        cams = Cameras.pinhole(c2w, fov_deg, width, height)
        threshold = settings.depth_mode == "threshold"
        img = render_image(self.model, cams, 0, cond=settings.condition,
                           supersample=None if full else 1,
                           thresholds=[settings.threshold] if threshold else [],
                           labels=settings.show == "labels")
        z, valid = depth_of(img, settings.depth_mode)
        if settings.show == "depth":
            out = colorize_depth(z, valid)
        elif settings.show == "opacity":
            out = to_uint8(np.repeat(img["opacity"][..., None], 3, -1))
        elif settings.show == "labels":
            out = colorize_labels(img["labels"].argmax(-1), self.model.label_head.n_classes)
        else:
            out = to_uint8(img["rgb"])
        return out, np.where(valid, z, np.inf).astype(np.float32)

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            job = self._next_job()
            if job is None:
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            client, state, key, full = job
            try:
                self._render_for(client, state, key, full)
            except Exception as err:  # a frame that fails must not stop the viewer
                log.exception("view: a frame failed")
                with self._lock:
                    state.rendered, state.rendered_full = key, True
                try:
                    client.add_notification("render failed", str(err), color="red")
                except Exception:
                    pass

    def _render_for(self, client, state: _ClientState, key: tuple, full: bool) -> None:
        cam = client.camera
        with self._lock:
            settings = Settings(**vars(self.settings))
            changed_at = state.changed_at
        c2w = c2w_from_viser(cam.wxyz, cam.position)
        aspect = float(cam.aspect) if cam.aspect and np.isfinite(cam.aspect) else 1.0
        height = settings.height if full else max(settings.height // self.preview_divisor, 8)
        width = max(int(round(height * aspect)), 8)
        t0 = time.perf_counter()
        image, z = self.render_view(c2w, float(np.degrees(cam.fov)), width, height, settings,
                                    full)
        render_s = time.perf_counter() - t0
        client.scene.set_background_image(image, format="png" if full else "jpeg",
                                          jpeg_quality=85, depth=z)
        sent = time.perf_counter()
        kind = "full" if full else "preview"
        stat = FrameStat(client.client_id, kind, width, height, render_s, sent - changed_at, sent)
        with self._lock:
            self.stats.append(stat)
            state.rendered, state.rendered_full = key, full
        self.gui_status.content = (f"frame {len(self.stats)}: {kind}, {width} x {height} px, "
                                   f"rendered in {render_s:.2f} s")

    # ------------------------------------------------------------------ lifetime

    def wait_for_frames(self, n: int, kind: str = "full", timeout: float = 60.0) -> list:
        """Block until ``n`` frames of ``kind`` were sent (for scripts and tests); returns them.
        TimeoutError otherwise."""
        deadline = time.perf_counter() + timeout
        while time.perf_counter() < deadline:
            with self._lock:
                done = [s for s in self.stats if s.kind == kind]
            if len(done) >= n:
                return done
            time.sleep(0.02)
        raise TimeoutError(f"{n} {kind} frame(s) not sent within {timeout:g} s")

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=30)
        self.server.stop()
