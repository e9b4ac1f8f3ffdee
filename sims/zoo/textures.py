"""Procedural textures of the zoo, made with numpy and OpenCV: (H, W, 3) uint8 RGB images.

Every function takes a ``numpy.random.Generator`` and is deterministic given its state, so a
scene's seed fixes its textures byte for byte. Fine detail is the point: wood grain (growth
rings warped by noise, with fibres), floor planks, tiles, wallpaper, printed labels (a brand
name, small print and a barcode), a cutting mat's grid, printed pages, grass and soil, building
facades and rows of books. Textures are written as PNG beside the scene's MJCF and used as 2d
textures (planes and the top faces of boxes) or cube textures (wrapped around primitives; those
must be square).
"""

from __future__ import annotations

import cv2
import numpy as np

#: Letters of the made-up words printed on labels and pages.
_CONSONANTS = "BCDFGHKLMNPRSTVZ"
_VOWELS = "AEIOU"


def smooth_noise(rng: np.random.Generator, height: int, width: int, cells_y: int,
                 cells_x: int) -> np.ndarray:
    """(H, W) float32 value noise in about [0, 1]: a ``cells_y`` x ``cells_x`` grid of random
    values interpolated bicubically."""
    grid = rng.random((max(cells_y, 1) + 1, max(cells_x, 1) + 1)).astype(np.float32)
    return cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)


def fractal_noise(rng: np.random.Generator, height: int, width: int, cells: int = 4,
                  octaves: int = 5) -> np.ndarray:
    """(H, W) float32 noise in [0, 1]: octaves of :func:`smooth_noise`, each twice as fine and
    half as strong as the one before, normalised."""
    total = np.zeros((height, width), np.float32)
    for k in range(octaves):
        n = cells * 2 ** k
        total += 0.5 ** k * smooth_noise(rng, height, width, min(n, height), min(n, width))
    lo, hi = float(total.min()), float(total.max())
    return (total - lo) / max(hi - lo, 1e-6)


def blend(a, b, t: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: colours ``a`` and ``b`` (RGB in [0, 1]) mixed by ``t`` (H, W) in [0, 1]."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    t = np.clip(t, 0.0, 1.0)[..., None]
    return to_uint8(a * (1.0 - t) + b * t)


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Colours in [0, 1] (float) to uint8."""
    return np.clip(np.rint(np.asarray(rgb, np.float32) * 255.0), 0, 255).astype(np.uint8)


def random_colour(rng: np.random.Generator, saturation=(0.4, 0.9), value=(0.5, 0.95)) -> np.ndarray:
    """(3,) RGB in [0, 1] of a random hue with saturation and value in the given ranges."""
    h = float(rng.uniform(0.0, 1.0))
    s, v = float(rng.uniform(*saturation)), float(rng.uniform(*value))
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _ink(rgb) -> tuple[int, int, int]:
    """An RGB colour in [0, 1] as the 0-255 tuple OpenCV draws with (our canvases are RGB, so
    the channel order stays as it is)."""
    c = to_uint8(rgb)
    return int(c[0]), int(c[1]), int(c[2])


def word(rng: np.random.Generator, syllables: int) -> str:
    """A made-up pronounceable word in capitals, e.g. ``"KATOMI"``."""
    return "".join(_CONSONANTS[rng.integers(len(_CONSONANTS))] + _VOWELS[rng.integers(len(_VOWELS))]
                   for _ in range(syllables))


def wood_grain(rng: np.random.Generator, height: int = 512, width: int = 512,
               light=(0.72, 0.53, 0.34), dark=(0.45, 0.29, 0.16)) -> np.ndarray:
    """Wood seen along the grain: growth rings around a centre off the image, stretched along x
    and warped by noise, dark late-wood bands, fibres along x and a little speckle."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x, y = x / max(height, width), y / max(height, width)
    cx, cy = rng.uniform(-0.5, 1.5), rng.uniform(-2.0, -0.6)
    stretch = rng.uniform(4.0, 9.0)
    warp = fractal_noise(rng, height, width, cells=3, octaves=4)
    r = np.sqrt(((x - cx) / stretch) ** 2 + (y - cy) ** 2)
    rings = r * rng.uniform(28.0, 48.0) + 2.5 * warp
    band = (rings - np.floor(rings)) ** 4
    fibres = smooth_noise(rng, height, width, height // 2, max(width // 48, 2))
    speckle = rng.random((height, width)).astype(np.float32)
    t = 0.6 * band + 0.25 * fibres + 0.15 * warp + 0.08 * (speckle - 0.5)
    return blend(light, dark, t)


def wood_planks(rng: np.random.Generator, size: int = 512, rows: int = 6) -> np.ndarray:
    """A floor of planks: ``rows`` rows across the image, each made of planks of random length
    cut from one grain image (shifted, brightened or darkened), dark seams between them."""
    hue = rng.uniform(-0.08, 0.08, 3)
    light = np.clip(np.array([0.74, 0.55, 0.36]) + hue, 0, 1)
    dark = np.clip(np.array([0.44, 0.29, 0.17]) + hue, 0, 1)
    grain = wood_grain(rng, size, size, light, dark).astype(np.float32)
    out = np.empty_like(grain)
    edges = np.linspace(0, size, rows + 1).astype(int)
    for r0, r1 in zip(edges[:-1], edges[1:]):
        x = 0
        while x < size:
            length = int(rng.integers(size // 3, size + 1))
            shift_y, shift_x = int(rng.integers(size)), int(rng.integers(size))
            piece = np.roll(grain, (shift_y, shift_x), axis=(0, 1))[r0:r1, x:x + length]
            out[r0:r1, x:x + length] = piece * rng.uniform(0.82, 1.12)
            out[r0:r1, x:x + 2] *= 0.45                          # butt joint
            x += length
        out[r0:r0 + 2] *= 0.4                                     # seam between rows
    return np.clip(out, 0, 255).astype(np.uint8)


def checker(size: int = 256, squares: int = 8, a=(0.9, 0.9, 0.88),
            b=(0.15, 0.15, 0.18)) -> np.ndarray:
    """A checkerboard of ``squares`` x ``squares`` squares."""
    idx = (np.arange(size) * squares // size)
    t = ((idx[:, None] + idx[None, :]) % 2).astype(np.float32)
    return blend(a, b, t)


def tiles(rng: np.random.Generator, size: int = 512, count: int = 6, base=None,
          grout=(0.75, 0.73, 0.7)) -> np.ndarray:
    """Square tiles, ``count`` per side, each a slightly different shade of ``base`` (seeded
    when None) with fine mottling, between grout lines; every other tile a second colour when
    the seed says so (a checker floor)."""
    base = random_colour(rng, (0.1, 0.5), (0.45, 0.9)) if base is None else np.asarray(base)
    second = random_colour(rng, (0.1, 0.6), (0.3, 0.8)) if rng.random() < 0.5 else base
    mottle = fractal_noise(rng, size, size, cells=8, octaves=4)
    img = np.empty((size, size, 3), np.float32)
    step = size / count
    for i in range(count):
        for j in range(count):
            colour = (base if (i + j) % 2 == 0 else second) * rng.uniform(0.9, 1.08)
            y0, y1, x0, x1 = int(i * step), int((i + 1) * step), int(j * step), int((j + 1) * step)
            img[y0:y1, x0:x1] = colour
    img *= (0.9 + 0.2 * mottle)[..., None]
    width = max(int(step * 0.05), 2)
    for k in range(count + 1):
        p = min(int(k * step), size - 1)
        img[max(p - width // 2, 0):p + width - width // 2] = grout
        img[:, max(p - width // 2, 0):p + width - width // 2] = grout
    return to_uint8(img)


def wallpaper(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A repeating wallpaper: a pale base colour with one seeded pattern (stripes, a lattice of
    diamonds, or dots with small flowers), fine paper noise."""
    base = random_colour(rng, (0.1, 0.35), (0.75, 0.95))
    ink = base * rng.uniform(0.45, 0.75)
    accent = random_colour(rng, (0.3, 0.7), (0.4, 0.8))
    img = np.ones((size, size, 3), np.float32) * base
    style = int(rng.integers(3))
    period = int(rng.choice([16, 32, 64]))
    y, x = np.mgrid[0:size, 0:size]
    if style == 0:                                      # stripes of two widths
        wide = (x % period) < period * rng.uniform(0.2, 0.45)
        thin = (x % period) == period - 3
        img[wide] = ink
        img[thin] = accent
    elif style == 1:                                    # diamond lattice
        u = np.abs((x % period) - period / 2) + np.abs((y % period) - period / 2)
        img[np.abs(u - period / 3) < 1.5] = ink
        img[u < period / 8] = accent
    else:                                               # dots and small flowers
        canvas = to_uint8(img)
        for cy in range(period // 2, size, period):
            for cx in range(period // 2 + (cy // period % 2) * period // 2, size + period, period):
                cv2.circle(canvas, (cx % size, cy), max(period // 6, 2), _ink(accent), -1,
                           cv2.LINE_AA)
                for a in range(5):
                    px = int(cx % size + period / 4 * np.cos(a * 2 * np.pi / 5))
                    py = int(cy + period / 4 * np.sin(a * 2 * np.pi / 5))
                    cv2.circle(canvas, (px, py), max(period // 12, 1), _ink(ink), -1, cv2.LINE_AA)
        img = canvas.astype(np.float32) / 255.0
    paper = rng.random((size, size)).astype(np.float32)
    img *= (0.94 + 0.06 * paper)[..., None]
    return to_uint8(img)


def barcode(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W) float32 barcode: 1 = black bar, 0 = white; bars and gaps of 1-4 modules."""
    modules = []
    while len(modules) < width:
        modules += [1] * int(rng.integers(1, 5)) + [0] * int(rng.integers(1, 4))
    row = np.asarray(modules[:width], np.float32)
    row[:3], row[-3:] = (1, 0, 1), (1, 0, 1)              # guard bars
    return np.repeat(row[None, :], height, axis=0)


def label(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A printed product label (square, for cube textures): a coloured background, a band with a
    made-up brand name, lines of small print, and a barcode with its digits on a white box."""
    bg = random_colour(rng, (0.3, 0.9), (0.55, 0.95))
    band = random_colour(rng, (0.5, 1.0), (0.2, 0.6))
    canvas = to_uint8(np.ones((size, size, 3)) * bg)
    s = size / 256.0
    cv2.rectangle(canvas, (0, int(30 * s)), (size, int(92 * s)), _ink(band), -1)
    brand = word(rng, int(rng.integers(2, 4)))
    scale = 1.6 * s * 6 / max(len(brand), 4)
    cv2.putText(canvas, brand, (int(10 * s), int(78 * s)), cv2.FONT_HERSHEY_DUPLEX, scale,
                _ink(np.ones(3) - 0.05), max(int(2 * s), 1), cv2.LINE_AA)
    ink = _ink(np.clip(bg * 0.25, 0, 1))
    for k in range(4):
        text = " ".join(word(rng, int(rng.integers(1, 4))).lower() for _ in range(3))
        cv2.putText(canvas, text, (int(10 * s), int((112 + 16 * k) * s)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.42 * s, ink, 1, cv2.LINE_AA)
    x0, y0, x1, y1 = int(60 * s), int(180 * s), int(236 * s), int(248 * s)
    cv2.rectangle(canvas, (x0 - 4, y0 - 4), (x1 + 4, y1 + 4), (255, 255, 255), -1)
    bars = barcode(rng, int(48 * s), x1 - x0)
    canvas[y0:y0 + bars.shape[0], x0:x1] = to_uint8(np.ones(3) - bars[..., None])
    digits = "".join(str(int(d)) for d in rng.integers(0, 10, 12))
    cv2.putText(canvas, digits, (x0, y1), cv2.FONT_HERSHEY_SIMPLEX, 0.5 * s, (0, 0, 0), 1,
                cv2.LINE_AA)
    return canvas


def cutting_mat(rng: np.random.Generator, size: int = 512, cells: int = 20) -> np.ndarray:
    """A cutting mat: a dark green or blue base with a fine grid (``cells`` per side), every
    fifth line bolder, and numbered ruler ticks along two edges."""
    base = np.array([0.12, 0.38, 0.25]) if rng.random() < 0.5 else np.array([0.12, 0.22, 0.45])
    base = base * rng.uniform(0.85, 1.15)
    canvas = to_uint8(np.ones((size, size, 3)) * base)
    line = _ink(np.clip(base + 0.35, 0, 1))
    bold = _ink(np.clip(base + 0.6, 0, 1))
    step = size / cells
    for k in range(cells + 1):
        p = int(round(k * step))
        colour, width = (bold, 2) if k % 5 == 0 else (line, 1)
        cv2.line(canvas, (p, 0), (p, size), colour, width)
        cv2.line(canvas, (0, p), (size, p), colour, width)
        if k % 2 == 0 and 0 < k < cells:
            cv2.putText(canvas, str(k), (p + 2, int(step * 0.8)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.3 * size / 512, bold, 1, cv2.LINE_AA)
            cv2.putText(canvas, str(k), (2, p - 2), cv2.FONT_HERSHEY_SIMPLEX,
                        0.3 * size / 512, bold, 1, cv2.LINE_AA)
    return canvas


def printed_page(rng: np.random.Generator, height: int = 512, width: int = 384) -> np.ndarray:
    """A printed page: off-white paper, a bold title, paragraphs of small made-up words and a
    box of numbers (a table)."""
    canvas = to_uint8(np.ones((height, width, 3)) * rng.uniform(0.88, 0.98))
    s = width / 384.0
    cv2.putText(canvas, word(rng, 3), (int(20 * s), int(44 * s)), cv2.FONT_HERSHEY_DUPLEX,
                1.0 * s, (20, 20, 30), 2, cv2.LINE_AA)
    y = int(74 * s)
    while y < height * 0.62:
        line = " ".join(word(rng, int(rng.integers(1, 4))).lower()
                        for _ in range(int(rng.integers(4, 8))))
        cv2.putText(canvas, line, (int(20 * s), y), cv2.FONT_HERSHEY_SIMPLEX, 0.38 * s,
                    (40, 40, 40), 1, cv2.LINE_AA)
        y += int(rng.choice([14, 14, 14, 28]) * s)
    x0, y0 = int(20 * s), int(height * 0.66)
    for r in range(6):
        for c in range(4):
            cv2.putText(canvas, f"{rng.integers(0, 1000):03d}", (x0 + c * int(80 * s),
                        y0 + r * int(22 * s) + int(16 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * s,
                        (30, 30, 90), 1, cv2.LINE_AA)
    cv2.rectangle(canvas, (x0 - 4, y0), (x0 + int(320 * s), y0 + int(136 * s)), (60, 60, 60), 1)
    return canvas


def ground(rng: np.random.Generator, size: int = 512, grassy: float | None = None) -> np.ndarray:
    """Grass and soil: fractal noise decides where soil shows through; blades of grass as fine
    per-pixel speckle. ``grassy`` in [0, 1] (seeded when None) is the share of grass."""
    grassy = float(rng.uniform(0.4, 0.9)) if grassy is None else grassy
    patches = fractal_noise(rng, size, size, cells=4, octaves=5)
    speckle = rng.random((size, size)).astype(np.float32)
    blades = smooth_noise(rng, size, size, size // 2, size // 2)
    grass_a = np.array([0.22, 0.42, 0.12]) * rng.uniform(0.85, 1.15)
    grass_b = np.array([0.42, 0.55, 0.2]) * rng.uniform(0.85, 1.15)
    soil_a, soil_b = np.array([0.42, 0.32, 0.22]), np.array([0.58, 0.48, 0.36])
    grass = blend(grass_a, grass_b, 0.6 * blades + 0.4 * speckle).astype(np.float32)
    soil = blend(soil_a, soil_b, 0.5 * speckle + 0.5 * patches).astype(np.float32)
    t = np.clip((patches - (1.0 - grassy)) * 8.0 + 0.5, 0.0, 1.0)[..., None]
    return np.clip(soil * (1 - t) + grass * t, 0, 255).astype(np.uint8)


def facade(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A building facade (square, for cube textures): a plaster or brick colour, floors of
    windows (dark glass, light frames, some lit), a band between floors."""
    wall = random_colour(rng, (0.05, 0.45), (0.45, 0.85))
    glass = np.array([0.16, 0.2, 0.28]) * rng.uniform(0.7, 1.3)
    lit = np.array([0.85, 0.78, 0.5])
    img = np.ones((size, size, 3), np.float32) * wall
    img *= (0.9 + 0.2 * fractal_noise(rng, size, size, cells=6, octaves=4))[..., None]
    floors, cols = int(rng.integers(4, 9)), int(rng.integers(3, 8))
    fh, cw = size / floors, size / cols
    for f in range(floors):
        y0 = int(f * fh)
        img[y0:y0 + max(int(fh * 0.06), 1)] *= 0.7
        for c in range(cols):
            x0 = int(c * cw + cw * 0.22)
            x1, ya, yb = int((c + 1) * cw - cw * 0.22), int(y0 + fh * 0.25), int(y0 + fh * 0.8)
            img[ya - 1:yb + 1, x0 - 1:x1 + 1] = 0.9
            img[ya:yb, x0:x1] = lit if rng.random() < 0.15 else glass
    return to_uint8(img)


def books(rng: np.random.Generator, size: int = 256, shelves: int = 4) -> np.ndarray:
    """Rows of book spines (square, for cube textures): ``shelves`` rows, each spine a random
    colour, width and height with a title stripe, the shelf's shadow behind."""
    img = np.ones((size, size, 3), np.float32) * 0.18
    row_h = size / shelves
    for r in range(shelves):
        x = 0
        y_floor = int((r + 1) * row_h) - 2
        while x < size:
            w = int(rng.integers(size // 40 + 2, size // 14 + 3))
            h = int(row_h * rng.uniform(0.55, 0.92))
            colour = random_colour(rng, (0.3, 0.85), (0.25, 0.85))
            img[y_floor - h:y_floor, x:x + w - 1] = colour
            stripe = y_floor - int(h * rng.uniform(0.5, 0.8))
            img[stripe:stripe + 3, x + 1:x + w - 2] = np.clip(colour + 0.4, 0, 1)
            x += w
        img[y_floor:y_floor + 2] = 0.35
    return to_uint8(img)


def speckled(rng: np.random.Generator, size: int = 256, colour=None,
             amount: float = 0.12) -> np.ndarray:
    """A mottled surface (plaster, stone, plastic): ``colour`` (seeded when None) with fractal
    noise and per-pixel speckle of relative strength ``amount``."""
    colour = random_colour(rng) if colour is None else np.asarray(colour)
    noise = fractal_noise(rng, size, size, cells=4, octaves=5)
    speckle = rng.random((size, size)).astype(np.float32)
    shade = 1.0 + amount * (1.4 * (noise - 0.5) + 0.6 * (speckle - 0.5))
    return to_uint8(colour[None, None, :] * shade[..., None])
