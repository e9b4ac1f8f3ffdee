"""Camera paths through keyframes (spline centres, slerp rotations) and the video writer's
formats, checked by decoding the files with the encoder package."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerfbot.ops.camera_path import interpolate_poses
from nerfbot.ops.cameras import look_at
from nerfbot.query.video import VIDEO_SUFFIXES, video_info, write_video


def _keys():
    eyes = [(2.0, 0.0, 1.0), (0.0, 2.0, 1.5), (-2.0, 0.0, 1.0), (0.0, -2.0, 0.5)]
    return np.stack([look_at(e, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)) for e in eyes])


def test_the_path_passes_through_its_keyframes_with_rotations():
    keys = _keys()
    poses = interpolate_poses(keys, 13)  # keyframes at frames 0, 4, 8, 12
    assert poses.shape == (13, 4, 4)
    np.testing.assert_allclose(poses[::4], keys, atol=1e-9)
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0, 0, 0, 1], (13, 4)))
    # slerp: halfway between two keyframes the rotation is halfway along the arc between them
    a, b = Rotation.from_matrix(keys[0, :3, :3]), Rotation.from_matrix(keys[1, :3, :3])
    half = Rotation.from_matrix(poses[2, :3, :3])
    assert (a.inv() * half).magnitude() == pytest.approx((a.inv() * b).magnitude() / 2, abs=1e-9)
    # centres move smoothly: no step is more than twice the mean step
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 2 * steps.mean()


def test_two_keyframes_give_a_straight_line_and_one_a_still_camera():
    keys = _keys()[:2]
    poses = interpolate_poses(keys, 5)
    np.testing.assert_allclose(poses[2, :3, 3], keys[:, :3, 3].mean(0), atol=1e-12)
    still = interpolate_poses(keys[:1], 3)
    np.testing.assert_allclose(still, np.repeat(keys[:1], 3, 0))
    np.testing.assert_allclose(interpolate_poses(keys[:, :3, :], 2), keys, atol=1e-9)  # (K, 3, 4)


def test_bad_keyframes_are_refused():
    with pytest.raises(ValueError, match="K >= 1"):
        interpolate_poses(np.zeros((0, 4, 4)), 5)
    with pytest.raises(ValueError, match="frames"):
        interpolate_poses(_keys(), 0)
    skew = _keys()
    skew[1, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="rotation"):
        interpolate_poses(skew, 5)


@pytest.mark.parametrize("suffix, codec", [(".mp4", "h264"), (".webm", "vp9"), (".gif", "gif")])
def test_videos_decode_with_the_codec_browsers_play(tmp_path, suffix, codec):
    frames = [np.full((33, 47, 3), 40 * i, np.uint8) for i in range(6)]  # odd sides
    path = write_video(tmp_path / f"v{suffix}", frames, fps=12)
    info = video_info(path)
    assert info["codec"] == codec and info["frames"] == 6
    if suffix != ".gif":
        assert info["pix_fmt"] == "yuv420p"  # the pixel format every browser decodes
        assert (info["width"], info["height"]) == (48, 34)  # padded to even sides
        assert info["fps"] == pytest.approx(12.0)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


def test_the_writer_refuses_what_it_cannot_write(tmp_path):
    frame = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match=".mov"):
        write_video(tmp_path / "v.mov", [frame])
    with pytest.raises(ValueError, match="no frames"):
        write_video(tmp_path / "v.mp4", [])
    with pytest.raises(ValueError, match="frame 1"):
        write_video(tmp_path / "w.mp4", [frame, np.zeros((6, 8, 3), np.uint8)])
    assert list(tmp_path.iterdir()) == []  # nothing half-written is left
    assert set(VIDEO_SUFFIXES) == {".mp4", ".webm", ".gif"}
