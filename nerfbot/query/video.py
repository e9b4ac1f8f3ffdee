"""Videos that browsers and Jupyter play, encoded with PyAV (FFmpeg's libraries).

``.mp4``: H.264 (libx264, yuv420p, the one profile every browser decodes); ``.webm``: VP9;
``.gif``: an animated GIF. Frames are RGB, all the same size; H.264 and VP9 need even sides, so
an odd row or column is repeated at the bottom or right edge.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import av
import numpy as np

from nerfbot.query.export import to_uint8

#: Video file suffix -> (PyAV codec, pixel format).
VIDEO_CODECS = {".mp4": ("libx264", "yuv420p"), ".webm": ("libvpx-vp9", "yuv420p"),
                ".gif": ("gif", "rgb8")}
#: The suffixes :func:`write_video` writes.
VIDEO_SUFFIXES = tuple(VIDEO_CODECS)


def _even(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 padded by edge repetition to even H and W."""
    h, w = img.shape[:2]
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(path, frames: Iterable[np.ndarray], fps: float = 24.0) -> Path:
    """Write RGB frames ((H, W, 3) float in [0, 1] or uint8, all the same size) to ``path``,
    whose suffix picks the format (:data:`VIDEO_CODECS`); atomically: the file appears only
    once every frame is written. ValueError for another suffix, no frames, or frames of
    different sizes."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_CODECS:
        raise ValueError(f"{path}: videos are written as {', '.join(VIDEO_SUFFIXES)}, "
                         f"not {path.suffix or 'a name without a suffix'}")
    codec, pix_fmt = VIDEO_CODECS[suffix]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp{os.getpid()}.{path.name}")
    container = av.open(str(tmp), mode="w")
    stream, size, n = None, None, 0
    try:
        for frame in frames:
            img = np.ascontiguousarray(frame if frame.dtype == np.uint8 else to_uint8(frame))
            if img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"{path}: frames must be (H, W, 3) RGB, got {img.shape}")
            if stream is None:
                size = img.shape[:2]
                # GIF frame delays are whole centiseconds
                rate = max(1, round(fps)) if suffix == ".gif" else \
                    Fraction(fps).limit_denominator(1001)
                stream = container.add_stream(codec, rate=rate)
                if suffix == ".gif":
                    stream.width, stream.height = size[1], size[0]
                else:
                    stream.width, stream.height = size[1] + size[1] % 2, size[0] + size[0] % 2
                    stream.options = {"crf": "18"} if codec == "libx264" else {"crf": "30",
                                                                              "b:v": "0"}
                stream.pix_fmt = pix_fmt
            elif img.shape[:2] != size:
                raise ValueError(f"{path}: frame {n} is {img.shape[1]}x{img.shape[0]}, the first "
                                 f"was {size[1]}x{size[0]}")
            if suffix != ".gif":
                img = _even(img)
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                container.mux(packet)
            n += 1
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    except BaseException:
        container.close()
        tmp.unlink(missing_ok=True)
        raise
    container.close()
    if n == 0:
        tmp.unlink(missing_ok=True)
        raise ValueError(f"{path}: no frames to write")
    os.replace(tmp, path)
    return path


def video_info(path) -> dict:
    """What a video file holds: {"codec", "pix_fmt", "width", "height", "frames", "fps"}
    (frames decoded and counted)."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        ctx = stream.codec_context
        frames = sum(1 for _ in container.decode(stream))
        return {"codec": ctx.name, "pix_fmt": ctx.pix_fmt, "width": ctx.width,
                "height": ctx.height, "frames": frames,
                "fps": float(stream.average_rate) if stream.average_rate else None}
