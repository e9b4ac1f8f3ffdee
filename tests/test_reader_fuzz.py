"""Dataset readers refuse bad input cleanly: a property-based fuzz of ``load_dataset`` (any
document gives a valid Dataset or a DatasetError, never another exception), and one unit test
per validation rule."""

from __future__ import annotations

import copy
import json
import logging
import math
import struct
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nerfbot.data import Dataset, DatasetError, load_dataset
from nerfbot.data.conditioning import dataset_conditioning, frame_conditions
from nerfbot.ops.cameras import look_at

W, H = 8, 6
FL = 7.0
NAN, INF = float("nan"), float("inf")
FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=list(HealthCheck))


# ----------------------------------------------------------------------------- files


def png_bytes(pixels: np.ndarray) -> bytes:
    """A PNG of (H, W) or (H, W, C) uint8 / uint16 pixels, C in 1..4 (grey, grey + alpha, RGB,
    RGBA): encoded here because OpenCV writes no 2-channel PNG."""
    a = pixels if pixels.ndim == 3 else pixels[:, :, None]
    h, w, c = a.shape
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    depth = 16 if a.dtype == np.uint16 else 8
    raw = b"".join(b"\x00" + row.astype(">u2" if depth == 16 else np.uint8).tobytes() for row in a)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


def npy_bytes(array) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=True)
    return buf.getvalue()


def _rgb(h=H, w=W, c=3, dtype=np.uint8) -> np.ndarray:
    top = 65535 if dtype == np.uint16 else 255
    return np.random.default_rng(h * w + c).integers(0, top, size=(h, w, c)).astype(dtype)


def _tiff_float() -> bytes:
    ok, buf = cv2.imencode(".tiff", np.random.default_rng(0).random((H, W, 3)).astype(np.float32))
    return buf.tobytes()


def _jpg() -> bytes:
    return cv2.imencode(".jpg", _rgb())[1].tobytes()


def _mask(value=255, h=H, w=W) -> np.ndarray:
    m = np.full((h, w), value, np.uint8)
    m[1:3, 2:5] = 0
    return m


#: File contents by kind: (extension, bytes). Names starting with "ok" are valid for their field.
FILES = {
    "image": {
        "ok_rgb8": (".png", lambda: png_bytes(_rgb())),
        "ok_grey8": (".png", lambda: png_bytes(_rgb(c=1))),
        "ok_grey_alpha8": (".png", lambda: png_bytes(_rgb(c=2))),
        "ok_rgba8": (".png", lambda: png_bytes(_rgb(c=4))),
        "ok_rgb16": (".png", lambda: png_bytes(_rgb(dtype=np.uint16))),
        "ok_grey_alpha16": (".png", lambda: png_bytes(_rgb(c=2, dtype=np.uint16))),
        "ok_jpg": (".jpg", _jpg),
        "wrong_size": (".png", lambda: png_bytes(_rgb(h=4, w=5))),
        "zero_byte": (".png", lambda: b""),
        "truncated": (".png", lambda: png_bytes(_rgb())[:40]),
        "text": (".png", lambda: b"not an image"),
        "float_tiff": (".tiff", _tiff_float),
        "npy": (".npy", lambda: npy_bytes(_rgb())),
    },
    "mask": {
        "ok_png": (".png", lambda: png_bytes(_mask())),
        "ok_npy": (".npy", lambda: npy_bytes(_mask() > 0)),
        "ok_rgb_png": (".png", lambda: png_bytes(np.repeat(_mask()[:, :, None], 3, 2))),
        "all_masked": (".png", lambda: png_bytes(_mask(0))),
        "wrong_size": (".png", lambda: png_bytes(_mask(h=3))),
        "npy_scalar": (".npy", lambda: npy_bytes(1.0)),
        "npy_object": (".npy", lambda: npy_bytes(np.array([{"a": 1}], dtype=object))),
        "npy_4d": (".npy", lambda: npy_bytes(np.ones((H, W, 1, 2)))),
        "zero_byte": (".npy", lambda: b""),
        "truncated_npy": (".npy", lambda: npy_bytes(np.ones((H, W)))[:60]),
    },
    "depth": {
        "ok_npy": (".npy", lambda: npy_bytes(np.full((H, W), 2.0, np.float32))),
        "ok_png16": (".png", lambda: png_bytes(np.full((H, W), 1500, np.uint16))),
        "ok_nan_inf": (".npy", lambda: npy_bytes(np.array([[NAN, INF] * (W // 2)] * H))),
        "negative": (".npy", lambda: npy_bytes(-np.ones((H, W), np.float32))),
        "int_npy": (".npy", lambda: npy_bytes(np.ones((H, W), np.int64))),
        "png8": (".png", lambda: png_bytes(np.ones((H, W), np.uint8))),
        "wrong_shape": (".npy", lambda: npy_bytes(np.ones((H, W, 2), np.float32))),
        "zero_byte": (".npy", lambda: b""),
    },
    "segmentation": {
        "ok_npy": (".npy", lambda: npy_bytes(np.zeros((H, W), np.int32))),
        "ok_png": (".png", lambda: png_bytes(np.ones((H, W), np.uint8))),
        "float": (".npy", lambda: npy_bytes(np.zeros((H, W)))),
        "huge_ids": (".npy", lambda: npy_bytes(np.full((H, W), 2**40, np.int64))),
        "uint64": (".npy", lambda: npy_bytes(np.full((H, W), 2**63, np.uint64))),
        "wrong_shape": (".npy", lambda: npy_bytes(np.zeros((2, 2), np.int32))),
    },
}

#: How a file is referred to: most keep it inside the dataset folder, some reach out.
STYLES = ("plain", "plain", "plain", "dot", "noext", "parent", "absolute", "symlink_out",
          "symlink_in", "dirlink_out", "backslash", "missing", "directory", "nul")


@dataclass(frozen=True)
class File:
    """A file to write when the document is materialised; replaced by its path string."""

    field: str
    kind: str
    style: str = "plain"


class Writer:
    """Materialises a drawn document under ``tmp``: the dataset in ``tmp/ds``, the files that
    paths should not reach in ``tmp/outside``."""

    def __init__(self, tmp: Path):
        self.root, self.outside = tmp / "ds", tmp / "outside"
        (self.root / "files").mkdir(parents=True)
        self.outside.mkdir()
        self.count = 0
        self.written: dict[int, tuple[File, str]] = {}

    def path(self, f: File) -> str:
        ext, make = FILES[f.field][f.kind]
        self.count += 1
        name = f"{f.field}{self.count}{ext}"
        inside = self.root / "files" / name
        target = self.outside / name if f.style in ("parent", "symlink_out", "dirlink_out") \
            else inside
        target.parent.mkdir(parents=True, exist_ok=True)
        if f.style != "missing":
            target.write_bytes(make())
        if f.style == "symlink_out":
            (self.root / "files" / f"link{name}").symlink_to(target)
            return f"files/link{name}"
        if f.style == "symlink_in":
            (self.root / f"link{name}").symlink_to(inside)
            return f"link{name}"
        if f.style == "dirlink_out" and not (self.root / "ext").exists():
            (self.root / "ext").symlink_to(self.outside, target_is_directory=True)
        return {"plain": f"files/{name}", "dot": f"./files/{name}", "noext": f"files/{name}",
                "parent": f"../outside/{name}", "absolute": str(inside),
                "dirlink_out": f"ext/{name}", "backslash": f"files\\{name}",
                "missing": f"files/{name}", "directory": "files", "nul": f"files/{name}\x00",
                }[f.style].removesuffix(ext if f.style == "noext" else "")

    def value(self, v, frames=None):
        """``v`` with every :class:`File` written and replaced by its path, and every
        :class:`FramePath` by the (already written) file_path of that frame in ``frames``."""
        if isinstance(v, File):  # one file per File object: a repeated frame repeats its path
            if id(v) not in self.written:
                self.written[id(v)] = (v, self.path(v))
            return self.written[id(v)][1]
        if isinstance(v, FramePath):
            f = frames[v.index] if isinstance(frames, list) and v.index < len(frames) else None
            return f.get("file_path") if isinstance(f, dict) else "files/none.png"
        if isinstance(v, dict):
            return {k: self.value(x, frames) for k, x in v.items()}
        if isinstance(v, list):
            return [self.value(x, frames) for x in v]
        return v

    def write_json(self, name: str, doc) -> None:
        if isinstance(doc, bytes):
            (self.root / name).write_bytes(doc)
            return
        if isinstance(doc, dict) and "frames" in doc:
            doc = {**doc, "frames": self.value(doc["frames"])}
        doc = self.value(doc, doc.get("frames") if isinstance(doc, dict) else None)
        (self.root / name).write_text(json.dumps(doc, allow_nan=True))


# ----------------------------------------------------------------------------- strategies
#
# A document is a valid base (random frame count, optional depth / masks / segmentation / time /
# joints / manifest / split lists) with 0 to 3 mutations: a field set to a malformed or extreme
# value, deleted, or the frames list, the JSON text or a split file broken.


def ring_pose(i: int, radius: float = 2.0) -> list:
    a = 2 * math.pi * i / 5
    return look_at([radius * math.cos(a), radius * math.sin(a), 0.7], [0, 0, 0]).tolist()


def _scaled(m: list, s: float) -> list:
    return [[v * s if c < 3 and r < 3 else v for c, v in enumerate(row)] for r, row in enumerate(m)]


def _translated(m: list, t) -> list:
    return [row[:3] + [t] for row in m[:3]] + [m[3]]


ODD_VALUES = st.sampled_from([None, True, "7", [], {}, "", 0, -1, NAN, INF, -INF, 1e300, -1e300,
                              1e-300, 10 ** 400, 2 ** 63, [1, 2], {"a": 1}])
ODD_NUMBERS = st.one_of(ODD_VALUES, st.floats(allow_nan=True, allow_infinity=True),
                        st.integers(-10 ** 20, 10 ** 20))
BAD_POSES = st.one_of(
    ODD_VALUES,
    st.just(ring_pose(1)[:3]),                                            # 3x4: accepted
    st.just([row[:3] for row in ring_pose(1)]),                           # 4x3
    st.just(_scaled(ring_pose(1), 2.0)),                                  # not rigid
    st.sampled_from([1e300, -1e300, 2e5, NAN, INF, 1e30, 10 ** 400]).map(
        lambda t: _translated(ring_pose(1), t)),
    st.just([[str(v) for v in row] for row in ring_pose(1)]),
    st.just(ring_pose(1)[:3] + [[0, 0, 0, 2]]),
    st.just(ring_pose(1, radius=600.0)),                                  # far from the scene
)
BAD_JOINTS = st.sampled_from([{}, {"other": 0.1}, {"hinge": 0.1, "slide": 0.0}, [0.1],
                              {"hinge": "x"}, {"hinge": NAN}, {"hinge": 10 ** 400}, None])
BAD_RANGES = st.sampled_from([[0.5], [1.0, 0.0], [0, 1, 2], [NAN, 1.0], [0, INF], "x", 3,
                              [0.2, 0.2], None, [True, False]])
CAMERA_MODELS = st.sampled_from(["OPENCV", "OPENCV_FISHEYE", "PINHOLE", "RADIAL", "EQUI", 5, None])
FILE_FIELDS = {"file_path": "image", "depth_file_path": "depth", "mask_path": "mask",
               "segmentation_path": "segmentation", "sensor_depth_file_path": "depth",
               "depth_path": "depth"}
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "x_fov",
               "y_fov", "k1", "k2", "k3", "k4", "p1", "p2", "camera_model", "is_fisheye")
SCENE_KEYS = ("bounds", "joint_info", "moving_joints", "objects", "geoms", "transparent_geoms",
              "part_bounds")
RAW_DOCUMENTS = st.sampled_from([b"not json", b"[1, 2]", b"\xff\xfe\x00", b"", b"[" * 100_000,
                                 b'{"frames": [' + b"1" * 5000 + b"]}", b"null", b"{"])


def good_file(field: str):
    return st.sampled_from(sorted(k for k in FILES[field] if k.startswith("ok"))).map(
        lambda kind: File(field, kind))


def bad_file(field: str):
    return st.one_of(st.builds(File, st.just(field), st.sampled_from(sorted(FILES[field])),
                               st.sampled_from(STYLES)), ODD_VALUES)


def bad_camera_value(key: str):
    if key == "camera_model":
        return CAMERA_MODELS
    return st.one_of(ODD_NUMBERS, st.floats(-4, 4), st.sampled_from([3.2, 1e-9, 179.0, 1e9]))


def bad_value(key: str):
    """Malformed or extreme values for a frame or top-level field."""
    if key in FILE_FIELDS:
        return bad_file(FILE_FIELDS[key])
    if key == "transform_matrix":
        return BAD_POSES
    if key == "joints":
        return BAD_JOINTS
    if key in CAMERA_KEYS:
        return bad_camera_value(key)
    if key.endswith("_filenames"):
        return st.one_of(ODD_VALUES, st.just(["files/none.png"]), st.just([FramePath(0)] * 2))
    if key == "scene":
        return ODD_VALUES
    if key == "joint_info":
        return st.one_of(ODD_VALUES, BAD_RANGES.map(lambda r: {"hinge": {"range": r}}),
                         st.just({"hinge": 3}))
    if key == "bounds":
        return st.one_of(ODD_VALUES, st.sampled_from([[[0, 0, 0], [0, 0, 0]], [[1, 1, 1], [0] * 3],
                                                      [[0, 0], [1, 1]], [[0, 0, NAN], [1] * 3]]))
    if key == "geoms":
        return st.one_of(ODD_VALUES, st.just({"x": "cube"}), st.just({"0": 5}))
    if key == "part_bounds":
        return st.one_of(ODD_VALUES, st.just([{"joints": "hinge"}]),
                         st.just([{"joints": ["hinge"], "bounds": [[1] * 3, [0] * 3]}]))
    if key in ("moving_joints", "objects", "transparent_geoms"):
        return st.one_of(ODD_VALUES, st.just(["nope"]), st.just([3]))
    return st.one_of(ODD_NUMBERS, st.floats(-2, 2))                     # time, scale factors


@dataclass(frozen=True)
class FramePath:
    """Placeholder for the file_path of frame ``index`` (for split lists)."""

    index: int


@st.composite
def frame_list(draw, n: int, keys: set, per_frame_intrinsics: bool):
    frames_ = []
    for i in range(n):
        f = {"file_path": draw(good_file("image")), "transform_matrix": ring_pose(i)}
        for key in sorted(keys & set(FILE_FIELDS)):
            f[key] = draw(good_file(FILE_FIELDS[key]))
        if "time" in keys:
            f["time"] = draw(st.floats(0, 1))
        if "joints" in keys:
            f["joints"] = {"hinge": draw(st.floats(-1, 1))}
        if per_frame_intrinsics:
            f.update(fl_x=FL + i, w=W, h=H)
        frames_.append(f)
    return frames_


def good_scene(joints: bool) -> dict:
    scene = {"bounds": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "objects": ["cube"],
             "geoms": {"0": "cube", "1": "floor"}, "transparent_geoms": []}
    if joints:
        scene.update(moving_joints=["hinge"], joint_info={"hinge": {"range": [-1.0, 1.0]}},
                     part_bounds=[{"joints": ["hinge"], "bounds": [[0, 0, 0], [1, 1, 1]]}])
    return scene


FRAME_EXTRAS = st.sets(st.sampled_from(["depth_file_path", "mask_path", "segmentation_path",
                                        "sensor_depth_file_path", "time", "joints"]), max_size=3)


@st.composite
def base_document(draw, blender: bool, keys: set) -> dict:
    """A valid transforms document (one Blender split file, or a nerfstudio file) whose frames
    carry the optional fields ``keys``."""
    n = draw(st.integers(1, 4))
    per_frame = not blender and draw(st.integers(0, 3)) == 0
    doc = {"frames": draw(frame_list(n, keys, per_frame))}
    if blender:
        doc["camera_angle_x"] = 0.69
    elif not per_frame:
        doc.update(fl_x=FL, w=W, h=H, **draw(st.fixed_dictionaries({}, optional={
            "fl_y": st.just(FL + 0.5), "cx": st.just(4.0), "cy": st.just(3.0),
            "camera_model": st.just("OPENCV"), "k1": st.sampled_from([0.0, 0.05, 0.4])})))
    if not blender and n > 1 and draw(st.booleans()):
        doc["train_filenames"] = [FramePath(i) for i in range(1, n)]
        doc["test_filenames"] = [FramePath(0)]
    if draw(st.booleans()):
        doc["scene"] = good_scene("joints" in keys)
    return doc


@st.composite
def mutated(draw_shared, doc: dict) -> object:
    """``doc`` with 0 to 3 mutations (mostly 1 or 2), each a field set to a bad value or
    deleted, or the structure broken."""
    def draw(strategy):  # a copy: sampled values are shared between examples
        return copy.deepcopy(draw_shared(strategy))

    for _ in range(draw(st.sampled_from([0, 1, 1, 1, 2, 2, 3]))):
        frames_ = doc.get("frames") if isinstance(doc, dict) else None
        what = draw(st.sampled_from(["frame", "frame", "frame", "top", "scene", "structure"]))
        if what == "frame" and isinstance(frames_, list) and frames_ and \
                isinstance(frames_[0], dict):
            f = frames_[draw(st.integers(0, len(frames_) - 1))]
            key = draw(st.sampled_from(sorted(FILE_FIELDS) + ["transform_matrix", "time",
                                                              "joints", *CAMERA_KEYS[:8]]))
            if draw(st.integers(0, 4)) == 0:
                f.pop(key, None)
            else:
                f[key] = draw(bad_value(key))
        elif what == "top" and isinstance(doc, dict):
            key = draw(st.sampled_from([*CAMERA_KEYS, "depth_unit_scale_factor", "scene",
                                        "train_filenames", "test_filenames", "val_filenames"]))
            doc[key] = draw(bad_value(key))
        elif what == "scene" and isinstance(doc, dict) and isinstance(doc.get("scene"), dict):
            key = draw(st.sampled_from(SCENE_KEYS))
            doc["scene"][key] = draw(bad_value(key))
        elif what == "structure" and isinstance(frames_, list):
            kind = draw(st.integers(0, 4))
            if kind == 0 and frames_:
                frames_.append(frames_[0])                               # a duplicate frame
            elif kind == 1:
                frames_.append(draw(ODD_VALUES))
            elif kind == 2:
                doc["frames"] = draw(ODD_VALUES)
            elif kind == 3:
                frames_.clear()
            else:
                return draw(RAW_DOCUMENTS)
    return doc


@st.composite
def nerfstudio_docs(draw):
    return draw(mutated(draw(base_document(False, draw(FRAME_EXTRAS)))))


@st.composite
def blender_docs(draw):
    """Split name -> document (mutations apply to one split file at a time)."""
    splits = draw(st.sets(st.sampled_from(["train", "val", "test"]), min_size=1))
    keys = draw(FRAME_EXTRAS)
    docs = {split: draw(base_document(True, keys)) for split in sorted(splits)}
    victim = draw(st.sampled_from(sorted(docs)))
    docs[victim] = draw(mutated(docs[victim]))
    return docs


# ----------------------------------------------------------------------------- the property


def assert_valid(ds: Dataset, conditioning=None) -> None:
    """Everything downstream relies on: shapes, dtypes, finite float32 cameras and rays,
    in-range splits, a proper box, a working conditioning."""
    n = len(ds)
    assert n >= 1 and len(ds.file_paths) == len(ds.alphas) == len(ds.depths) == n
    assert len(ds.masks) == len(ds.segmentations) == n
    assert ds.c2w.shape == (n, 4, 4) and ds.intrinsics.shape == (n, 4) and ds.sizes.shape == (n, 2)
    for i, img in enumerate(ds.images):
        w, h = (int(v) for v in ds.sizes[i])
        assert img.dtype == np.uint8 and img.shape == (h, w, 3)
        for extra in (ds.masks[i], ds.depths[i], ds.segmentations[i]):
            assert extra is None or extra.shape == (h, w)
        assert ds.masks[i] is None or ds.masks[i].dtype == bool
    assert np.isfinite(ds.c2w.astype(np.float32)).all()
    assert np.isfinite(ds.intrinsics.astype(np.float32)).all() and (ds.intrinsics[:, :2] > 0).all()
    cams = ds.cameras()
    for i in range(n):
        rays = cams.rays(i)
        assert rays.origins.isfinite().all() and rays.directions.isfinite().all()
    assert all(0 <= i < n for idx in ds.splits.values() for i in idx)
    assert np.isfinite(ds.aabb).all() and (ds.aabb[0] < ds.aabb[1]).all()
    if ds.times is not None:
        assert ((ds.times >= 0) & (ds.times <= 1)).all()
    conds = frame_conditions(ds, conditioning or dataset_conditioning(ds))
    assert conds is None or np.isfinite(conds).all()


def load_or_refuse(path: Path) -> None:
    """load_dataset (and the dataset's conditioning) either give a valid dataset or raise a
    one-line DatasetError; anything else fails the test."""
    try:
        ds = load_dataset(path)
        conditioning = dataset_conditioning(ds)
    except DatasetError as e:
        assert "\n" not in str(e)
        return
    assert_valid(ds, conditioning)


@FUZZ
@given(doc=nerfstudio_docs())
def test_fuzz_nerfstudio_reader_gives_a_dataset_or_a_dataset_error(doc):
    with tempfile.TemporaryDirectory() as tmp:
        w = Writer(Path(tmp))
        w.write_json("transforms.json", doc)
        load_or_refuse(w.root)


@FUZZ
@given(docs=blender_docs())
def test_fuzz_blender_reader_gives_a_dataset_or_a_dataset_error(docs):
    with tempfile.TemporaryDirectory() as tmp:
        w = Writer(Path(tmp))
        for split, doc in docs.items():
            w.write_json(f"transforms_{split}.json", doc)
        load_or_refuse(w.root)


def test_fuzz_documents_include_valid_datasets():
    """The property is not vacuous: a valid document of each layout loads and passes
    :func:`assert_valid`."""
    with tempfile.TemporaryDirectory() as tmp:
        w = Writer(Path(tmp))
        frames_ = [{"file_path": File("image", "ok_rgb8"), "transform_matrix": ring_pose(i),
                    "mask_path": File("mask", "ok_png"), "depth_file_path": File("depth", "ok_npy")}
                   for i in range(3)]
        w.write_json("transforms.json", {"fl_x": FL, "w": W, "h": H, "frames": frames_})
        assert_valid(load_dataset(w.root))
    with tempfile.TemporaryDirectory() as tmp:
        w = Writer(Path(tmp))
        for split in ("train", "test"):
            w.write_json(f"transforms_{split}.json", {"camera_angle_x": 0.69, "frames": [
                {"file_path": File("image", "ok_rgba8", "noext"), "transform_matrix": ring_pose(i),
                 "time": i / 2} for i in range(3)]})
        assert_valid(load_dataset(w.root))


# ----------------------------------------------------------------------------- one test per rule


def _dataset(root: Path, n: int = 4, radius: float = 2.0, **top) -> dict:
    """A valid nerfstudio dataset of ``n`` 8x6 frames on a ring; returns its document."""
    root.mkdir(parents=True, exist_ok=True)
    frames_ = []
    for i in range(n):
        (root / f"f{i}.png").write_bytes(png_bytes(_rgb(c=3) + i))
        frames_.append({"file_path": f"f{i}.png", "transform_matrix": ring_pose(i, radius)})
    doc = {"fl_x": FL, "w": W, "h": H, "frames": frames_, **top}
    _save(root, doc)
    return doc


def _save(root: Path, doc: dict) -> None:
    (root / "transforms.json").write_text(json.dumps(doc, allow_nan=True))


def test_missing_split_is_a_dataset_error_naming_the_available_splits(tmp_path):
    _dataset(tmp_path)
    ds = load_dataset(tmp_path)
    with pytest.raises(DatasetError, match=r"no 'val' split \(available: test, train\)"):
        ds.indices("val")
    assert ds.indices("test") == [0]


def test_only_a_test_split_refuses_training_in_one_line(tmp_path):
    """A Blender folder with only transforms_test.json: training says there is no train split."""
    from nerfbot.train.trainer import TrainConfig, Trainer

    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "r_0.png").write_bytes(png_bytes(_rgb()))
    (tmp_path / "transforms_test.json").write_text(json.dumps(
        {"camera_angle_x": 0.69, "frames": [{"file_path": "./test/r_0",
                                             "transform_matrix": ring_pose(0)}]}))
    ds = load_dataset(tmp_path)
    with pytest.raises(DatasetError, match=r"no 'train' split \(available: test\)"):
        Trainer(ds, tmp_path / "run", TrainConfig(method="ngp", max_steps=1, progress=False))


@pytest.mark.parametrize("field", ["file_path", "mask_path", "depth_file_path"])
def test_symlinks_out_of_the_root_are_refused(tmp_path, field):
    root, outside = tmp_path / "ds", tmp_path / "outside"
    doc = _dataset(root)
    outside.mkdir()
    payload = {"file_path": png_bytes(_rgb()), "mask_path": png_bytes(_mask()),
               "depth_file_path": npy_bytes(np.ones((H, W), np.float32))}[field]
    ext = ".npy" if field == "depth_file_path" else ".png"
    (outside / f"x{ext}").write_bytes(payload)
    (root / f"link{ext}").symlink_to(outside / f"x{ext}")
    doc["frames"][1][field] = f"link{ext}"
    _save(root, doc)
    with pytest.raises(DatasetError, match=rf"frames\[1\]\.{field}: .*link{ext} resolves to "
                                           r".*outside.*, outside the dataset folder"):
        load_dataset(root)
    # a linked folder, and the extension Blender paths omit, are followed too
    (root / "shared").symlink_to(outside, target_is_directory=True)
    doc["frames"][1][field] = f"shared/x{ext}"[: -4 if field == "file_path" else None]
    _save(root, doc)
    with pytest.raises(DatasetError, match=rf"frames\[1\]\.{field}: .* outside the dataset"):
        load_dataset(root)


def test_symlinks_inside_the_root_and_a_linked_root_are_accepted(tmp_path):
    root = tmp_path / "real"
    doc = _dataset(root)
    (root / "alias.png").symlink_to(root / "f2.png")
    doc["frames"][2]["file_path"] = "alias.png"
    _save(root, doc)
    (tmp_path / "link").symlink_to(root, target_is_directory=True)
    ds = load_dataset(tmp_path / "link")
    assert ds.file_paths[2] == "alias.png" and len(ds) == 4


@pytest.mark.parametrize("translation, message", [
    (1e300, r"camera position .* beyond 100000 m of the origin"),
    (2e5, r"camera position .* beyond 100000 m"),
    (NAN, r"non-finite"),
    (10 ** 400, r"expected a 4x4 matrix"),
])
def test_poses_of_implausible_scale_are_refused(tmp_path, translation, message):
    doc = _dataset(tmp_path)
    for row in doc["frames"][2]["transform_matrix"][:3]:
        row[3] = translation
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=rf"frames\[2\]\.transform_matrix: .*{message}"):
        load_dataset(tmp_path)


def test_cameras_far_from_the_manifest_scene_are_refused(tmp_path):
    """Poses written in millimetres around a 1 m scene are caught; a 100 m yard seen from 150 m
    and a tabletop seen from 3 m pass."""
    scene = {"bounds": [[-0.5, -0.5, 0.0], [0.5, 0.5, 0.5]]}
    _dataset(tmp_path / "table", radius=3.0, scene=scene)
    assert load_dataset(tmp_path / "table").aabb_source == "manifest"
    _dataset(tmp_path / "mm", radius=3000.0, scene=scene)
    with pytest.raises(DatasetError, match=r"frames\[0\]\.transform_matrix: camera is 3000 m from "
                                           r"the centre of the scene bounds"):
        load_dataset(tmp_path / "mm")
    yard = {"bounds": [[-50.0, -50.0, 0.0], [50.0, 50.0, 10.0]]}
    _dataset(tmp_path / "yard", radius=150.0, scene=yard)
    assert len(load_dataset(tmp_path / "yard")) == 4
    _dataset(tmp_path / "unbounded", radius=9e4)          # no manifest: only the 1e5 m limit
    assert len(load_dataset(tmp_path / "unbounded")) == 4


def test_duplicate_files_and_split_overlap_are_warnings(tmp_path, caplog):
    doc = _dataset(tmp_path)
    doc["frames"][3]["file_path"] = "./f1.png"
    doc["train_filenames"] = ["f0.png", "f1.png", "f2.png"]
    doc["test_filenames"] = ["f2.png"]
    _save(tmp_path, doc)
    with caplog.at_level(logging.WARNING, logger="nerfbot.data"):
        ds = load_dataset(tmp_path)
    assert len(ds) == 4
    text = caplog.text
    assert "2 frames use the same image file" in text and "frames[1]; " in text
    assert "frames[3]" in text
    assert "1 of 1 'test' frames are also training images" in text and "frames[2]" in text


def test_joint_names_must_agree_between_frames(tmp_path):
    doc = _dataset(tmp_path)
    for k, fr in enumerate(doc["frames"]):
        fr["joints"] = {"hinge": 0.1 * k, "slide": 0.0}
    doc["frames"][2]["joints"] = {"hinge": 0.2}
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=r"frames\[2\]\.joints: joint names \['hinge'\] differ "
                                           r"from .*frames\[0\]'s \['hinge', 'slide'\]"):
        load_dataset(tmp_path)
    doc["frames"][2]["joints"] = {}
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=r"frames\[2\]\.joints: expected a non-empty object"):
        load_dataset(tmp_path)


@pytest.mark.parametrize("limits, message", [
    ([0.5], r"expected \[lo, hi\]"),
    ([0.0, 1.0, 2.0], r"expected \[lo, hi\]"),
    ([1.0, -1.0], r"reversed range \[1, -1\]"),
    ([NAN, 1.0], r"\[0\]: must be finite"),
    ("0..1", r"expected \[lo, hi\]"),
])
def test_bad_manifest_joint_ranges_are_refused(tmp_path, limits, message):
    doc = _dataset(tmp_path)
    for k, fr in enumerate(doc["frames"]):
        fr["joints"] = {"hinge": 0.1 * k}
    doc["scene"] = {"moving_joints": ["hinge"], "joint_info": {"hinge": {"range": limits}}}
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=rf"transforms\.json: scene\.joint_info\.hinge\.range"
                                           rf".*{message}"):
        load_dataset(tmp_path)


def test_joint_conditioning_errors_name_the_file(tmp_path):
    doc = _dataset(tmp_path)
    for k, fr in enumerate(doc["frames"]):
        fr["joints"] = {"hinge": 0.1 * k}
    doc["scene"] = {"moving_joints": ["hinge"], "joint_info": {"hinge": {"range": None}}}
    _save(tmp_path, doc)
    ds = load_dataset(tmp_path)
    assert dataset_conditioning(ds).ranges == ((0.0, pytest.approx(0.3)),)
    ds.manifest["joint_info"]["hinge"]["range"] = [2.0, 1.0]        # edited in memory
    with pytest.raises(DatasetError, match=r"transforms\.json: scene\.joint_info\.hinge\.range: "
                                           r"reversed"):
        dataset_conditioning(ds)
    ds.manifest = {"moving_joints": ["hinge", "elbow"]}
    with pytest.raises(DatasetError, match=r"transforms\.json: scene\.moving_joints: 'elbow' not "
                                           r"given by the frames \(their joints: hinge\)"):
        dataset_conditioning(ds)


@pytest.mark.parametrize("key, value, field", [
    ("fl_x", 1e300, "fl_x"), ("fl_x", 1e-300, "fl_x"), ("fl_x", 10 ** 400, "fl_x"),
    ("cx", 1e300, "cx"), ("camera_angle_x", 1e-30, "camera_angle_x"),
])
def test_implausible_intrinsics_are_refused(tmp_path, key, value, field):
    doc = _dataset(tmp_path)
    if key == "camera_angle_x":
        del doc["fl_x"]
    doc[key] = value
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=rf"transforms\.json: {field}: "):
        load_dataset(tmp_path)


@pytest.mark.parametrize("coeffs, field", [({"k1": 1e6}, "k1"), ({"k1": -1e6}, "k1"),
                                           ({"k1": 0.1, "k2": 1e300}, "k2")])
def test_absurd_distortion_is_refused(tmp_path, coeffs, field):
    doc = _dataset(tmp_path)
    doc.update(camera_model="OPENCV", **coeffs)
    _save(tmp_path, doc)
    with pytest.raises(DatasetError, match=rf"transforms\.json: {field}: OPENCV distortion .* "
                                           r"leaves 0\.0% of the 8x6 image with source pixels"):
        load_dataset(tmp_path)


def test_bad_manifest_fields_nerfbot_reads_are_refused(tmp_path):
    doc = _dataset(tmp_path)
    for bad, field in (({"geoms": ["cube"]}, "geoms"), ({"objects": "cube"}, "objects"),
                       ({"joint_info": {"hinge": 3}}, r"joint_info\.hinge"),
                       ({"part_bounds": [{"joints": ["a"], "bounds": [[1, 1, 1], [0, 0, 0]]}]},
                        r"part_bounds\[0\]\.bounds")):
        doc["scene"] = bad
        _save(tmp_path, doc)
        with pytest.raises(DatasetError, match=rf"transforms\.json: scene\.{field}: "):
            load_dataset(tmp_path)


def test_unreadable_json_variants_are_dataset_errors(tmp_path):
    _dataset(tmp_path)
    for text in ("[" * 100_000, '{"frames": [' + "1" * 5000 + "]}"):
        (tmp_path / "transforms.json").write_text(text)
        with pytest.raises(DatasetError, match=r"transforms\.json: invalid JSON"):
            load_dataset(tmp_path)


def test_cli_reports_a_missing_train_split_in_one_line(tmp_path, capsys):
    from nerfbot.app.cli import main

    doc = _dataset(tmp_path / "ds")
    doc["test_filenames"] = ["f0.png"]
    _save(tmp_path / "ds", doc)
    code = main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "run"),
                 "--max-steps", "1", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "no 'train' split (available: test)" in err, err


def test_cli_trains_a_one_frame_dataset_without_test_metrics_and_eval_refuses(tmp_path, capsys,
                                                                              caplog):
    """The only frame trains (a warning says there is no test frame); evaluating the empty
    test split is a one-line error, not NaN."""
    from nerfbot.app.cli import main

    doc = _dataset(tmp_path / "ds", n=1)
    assert main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "run"),
                 "--max-steps", "1", "--no-progress", "--option", "log2_hashmap_size=12"]) == 0
    out = capsys.readouterr()
    assert "no 'test' frame" in caplog.text and json.loads(out.out)["steps"] == 1
    assert "psnr" not in json.loads(out.out)
    assert main(["eval", str(tmp_path / "run"), "--data", str(tmp_path / "ds"), "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the 'test' split is empty; nothing to evaluate" in err, err
    assert doc["frames"]
