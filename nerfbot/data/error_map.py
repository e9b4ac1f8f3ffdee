"""Where training still fails: a running per-tile error of the training frames, and draws of
training pixels in proportion to it (Instant-NGP's error-map sampling).

Each training frame is cut into square tiles of ``tile`` pixels a side (smaller at the right
and bottom edges). Tile ``t`` keeps e_t, a running mean of the squared colour error of its
pixels as training draws them; a draw picks tile ``t`` with probability e_t A_t / sum_s e_s A_s
(A_t its pixel count), then a pixel of the tile uniformly, so that pixel ``p`` in tile ``t`` is
drawn with probability e_t / sum_s e_s A_s. Tiles start at an error of 1 (an image's MSE is
at most 1), so draws sweep the tiles nobody has looked at before they settle where the error is.

Fine texture seen by few of the cameras (wallpaper from close by, small moving objects) is a
small share of the pixels and gets few of a uniform batch's rays; its error stays high, and the
map sends rays there.
"""

from __future__ import annotations

import math

import torch


class ErrorMap:
    """Running per-tile training error of a set of frames of sizes ``widths`` x ``heights``
    (F,) pixels, whose pixels are numbered frame after frame from ``offsets`` (F + 1,) (a
    :class:`~nerfbot.data.pixels.PixelBank`'s flat order).

    ``rate``: the weight of a batch's mean error in a tile against the tile's running value."""

    def __init__(self, widths: torch.Tensor, heights: torch.Tensor, offsets: torch.Tensor,
                 tile: int = 8, rate: float = 0.5, device="cpu"):
        if isinstance(tile, bool) or not isinstance(tile, int) or tile < 1:
            raise ValueError(f"error map tile must be an integer >= 1 pixels, got {tile!r}")
        if not 0.0 < rate <= 1.0:
            raise ValueError(f"error map rate must be in (0, 1], got {rate}")
        self.tile, self.rate = tile, float(rate)
        self.device = torch.device(device)
        widths, heights = widths.long().cpu(), heights.long().cpu()
        self.tiles_x = (widths + tile - 1) // tile
        """(F,) tiles per row of each frame."""
        tiles_y = (heights + tile - 1) // tile
        counts = self.tiles_x * tiles_y
        self.tile_offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(counts, 0)])
        """(F + 1,) index of each frame's first tile."""
        n = int(self.tile_offsets[-1])
        frame = torch.repeat_interleave(torch.arange(len(widths)), counts)
        local = torch.arange(n) - self.tile_offsets[frame]
        tx, ty = local % self.tiles_x[frame], local // self.tiles_x[frame]
        x0, y0 = tx * tile, ty * tile
        self._frame = frame.to(self.device)
        self._x0, self._y0 = x0.to(self.device), y0.to(self.device)
        self._w = torch.minimum(widths[frame] - x0, torch.tensor(tile)).to(self.device)
        self._h = torch.minimum(heights[frame] - y0, torch.tensor(tile)).to(self.device)
        self._width = widths[frame].to(self.device)
        self._frame_width = widths.to(self.device)
        self._frame_tiles_x = self.tiles_x.to(self.device)
        self._frame_first_tile = self.tile_offsets[:-1].to(self.device)
        self._offsets = offsets.long().to(self.device)
        self.area = (self._w * self._h).double()
        """(T,) pixels of each tile."""
        self.error = torch.ones(n, dtype=torch.float64, device=self.device)
        """(T,) running mean squared colour error of each tile's drawn pixels (1 = not yet
        seen)."""
        self._cdf = torch.cumsum(self.error * self.area, 0)

    def __len__(self) -> int:
        return int(self.error.shape[0])

    def tiles_of(self, pixels: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        """(n,) tile of each of ``pixels`` (n,) (flat indices) in frame slots ``slots`` (n,)."""
        local = pixels - self._offsets[slots]
        width = self._frame_width[slots]
        ty, tx = (local // width) // self.tile, (local % width) // self.tile
        return self._frame_first_tile[slots] + ty * self._frame_tiles_x[slots] + tx

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """(n,) flat pixel indices drawn with probability :meth:`probability`."""
        cdf = self._cdf
        u = torch.rand(n, generator=generator, dtype=torch.float64).to(self.device) * cdf[-1]
        t = torch.searchsorted(cdf, u, right=True).clamp_(max=len(cdf) - 1)
        r = torch.rand((n, 2), generator=generator).to(self.device)
        x = self._x0[t] + (r[:, 0] * self._w[t]).long().minimum(self._w[t] - 1)
        y = self._y0[t] + (r[:, 1] * self._h[t]).long().minimum(self._h[t] - 1)
        return self._offsets[self._frame[t]] + y * self._width[t] + x

    def probability(self, pixels: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        """(n,) float64 probability that one :meth:`draw` gives each of ``pixels`` (n,)."""
        return self.error[self.tiles_of(pixels, slots)] / self._cdf[-1]

    def update(self, pixels: torch.Tensor, slots: torch.Tensor, errors: torch.Tensor) -> None:
        """Fold the squared colour errors ``errors`` (n,) of ``pixels`` (n,) (frame slots
        ``slots``) into their tiles: e_t <- e_t + (1 - (1 - rate)^k) (mean - e_t), k of the
        batch's pixels in tile t, ``mean`` their mean error. Non-finite errors are ignored."""
        keep = torch.isfinite(errors)
        if not bool(keep.all()):
            pixels, slots, errors = pixels[keep], slots[keep], errors[keep]
        if not len(pixels):
            return
        t = self.tiles_of(pixels, slots)
        size = len(self)
        count = torch.bincount(t, minlength=size)
        total = torch.bincount(t, weights=errors.double(), minlength=size)
        hit = count > 0
        mean = total[hit] / count[hit]
        step = 1.0 - (1.0 - self.rate) ** count[hit].double()
        self.error[hit] += step * (mean - self.error[hit])
        self._cdf = torch.cumsum(self.error * self.area, 0)

    def summary(self) -> str:
        """One line: the share of the error held by the tenth of the tiles that hold most."""
        k = max(1, math.ceil(len(self) / 10))
        mass = self.error * self.area
        top = torch.topk(mass, k).values.sum() / mass.sum()
        return f"{len(self)} tiles of {self.tile} px; the top 10 % hold {100 * float(top):.0f} % of the error"
