"""Semantic-NeRF's label branch for any static model: class logits at a point from its
position and the field's geometry features (position only: the branch sits before the view
direction, so a surface has one label from every side), composited along rays like colour.

A model carries a :class:`LabelHead` as ``model.label_head`` (:func:`attach_label_head`; runs
trained with labels rebuild it from their spec). Renderers that support labels keep each
sample's point and features in :attr:`RenderOutput.positions` / ``features``;
:func:`render_labels` turns them into per-ray class probabilities, :func:`point_labels`
answers at arbitrary points.
"""

from __future__ import annotations

import copy
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.data.labels import BACKGROUND, LabelClasses
from nerfbot.fields.base import BoxNormalizer, mlp
from nerfbot.ops.encodings import FrequencyEncoding
from nerfbot.ops.rendering import RenderOutput, accumulate

#: Hidden width of the label MLP.
LABEL_HIDDEN = 64
#: Frequencies of the label head's positional encoding: low, so that labels vary smoothly in
#: space and a few labelled pixels spread over their object; edges come from the features.
LABEL_FREQS = 2
#: Initial background-class logit of an empty ray's rest transmittance.
BACKGROUND_LOGIT = 4.0


class LabelHead(nn.Module):
    """Class logits at world points: (M, 3) positions and (M, C) geometry features of the
    field -> (M, K) logits of the K ``classes``.

    Semantic-NeRF's label branch, position only (before the view direction: a surface has
    one label from every side): an MLP (two hidden ReLU layers) over a low-frequency
    encoding of the position in the field's cube and the field's geometry features. The
    features enter detached, so labels never change the colour or density the field learns
    from the images; through them a label spreads to what looks and is shaped alike.

    Logits are composited along a ray as in Semantic-NeRF, and the rest of a ray's
    transmittance carries ``background_logits`` (K,), learned, starting in favour of the
    :data:`~nerfbot.data.labels.BACKGROUND` class (what the learned background shows: sky).
    Because logits are unbounded, a surface the field has left half transparent can still
    outvote the background where the labels say it is there.
    """

    def __init__(self, normalize: nn.Module, feature_dim: int, classes: LabelClasses,
                 hidden: int = LABEL_HIDDEN, n_freqs: int = LABEL_FREQS):
        super().__init__()
        if len(classes) < 2:
            raise ValueError(f"labels need at least 2 classes, got {list(classes.names)}")
        self.classes = classes
        self.n_classes = len(classes)
        self.background_class = classes.index(BACKGROUND)
        self.normalize = normalize
        self.encoding = FrequencyEncoding(3, n_freqs)
        self.net = mlp(self.encoding.out_dim + feature_dim, hidden, 2, self.n_classes)
        start = torch.zeros(self.n_classes)
        start[self.background_class] = BACKGROUND_LOGIT
        self.background_logits = nn.Parameter(start)

    def forward(self, x: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        """x: (M, 3) world points, feat: (M, C) -> (M, K) logits."""
        unit = self.normalize(x.float()).clamp(0.0, 1.0)
        return self.net(torch.cat([self.encoding(2.0 * unit - 1.0), feat.detach().float()], -1))

    def probabilities(self, x: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        """(M, K) class probabilities at points x (M, 3) with field features (M, C)."""
        return F.softmax(self(x, feat), dim=-1)


def render_labels(head: LabelHead, out: RenderOutput, rays: Optional[slice] = None
                  ) -> torch.Tensor:
    """(R, K) class probabilities of rendered rays: the softmax of sum_i w_i s_i over each
    ray's sample logits s_i plus its remaining transmittance times the head's
    ``background_logits``. Each row sums to 1; an empty ray shows softmax(background_logits).

    The weights w_i enter detached: a label loss trains the head and the features under it
    but never moves density, so sparse or wrong labels cannot pull surfaces towards the
    camera (geometry comes from the images alone).

    ``rays``: only the rays of this slice (start:stop of the R rays; the label head then runs
    on their samples alone). Raises ValueError when the renderer kept no sample features."""
    start, stop, _ = (rays or slice(None)).indices(out.opacity.shape[0])
    opacity = out.opacity[start:stop].float()
    n = stop - start
    index = out.ray_indices
    bounds = torch.tensor([start, stop], dtype=index.dtype, device=index.device)
    lo, hi = (int(v) for v in torch.searchsorted(index, bounds))
    if hi == lo:
        logits = opacity.new_zeros(n, head.n_classes)
    elif out.features is None or out.positions is None:
        raise ValueError("this renderer keeps no sample features: labels need a method "
                         "marched over an occupancy grid (ngp, plenoxels, tensorf, ...) or nerf")
    else:
        logits = accumulate(out.weights[lo:hi].detach(),
                            head(out.positions[lo:hi], out.features[lo:hi]),
                            index[lo:hi] - start, n).float()
    rest = (1.0 - opacity.detach()).clamp_min(0.0)
    return F.softmax(logits + rest[:, None] * head.background_logits.float(), dim=-1)


def label_loss(probs: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of per-pixel class probabilities (P, K) against class indices (P,)
    (entries < 0 ignored); 0 (with a gradient graph) when no pixel is labelled."""
    keep = target >= 0
    if not bool(keep.any()):
        return probs.sum() * 0.0
    p = probs[keep].gather(1, target[keep].long()[:, None]).squeeze(1)
    return -torch.log(p.clamp_min(1e-6)).mean()


@torch.no_grad()
def point_labels(model: nn.Module, x: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
    """(N, K) class probabilities at world points ``x`` (N, 3) of a model with a label head
    (static: the field's features without a condition); ValueError without one."""
    head = model.label_head
    if head is None:
        raise ValueError("this run has no label head (train it with --labels)")
    x = torch.as_tensor(x, dtype=torch.float32, device=model.aabb.device).reshape(-1, 3)
    out = [head.probabilities(part, model.field.density(part)[1]) for part in x.split(chunk)]
    return torch.cat(out) if out else x.new_zeros(0, head.n_classes)


def feature_dim(model: nn.Module) -> int:
    """Width C of ``model.field``'s geometry features, from one probe at the bounds' centre."""
    centre = model.aabb.mean(0, keepdim=True)
    with torch.no_grad():
        _, feat = model.field.density(centre)
    return int(feat.shape[-1])


def attach_label_head(model: nn.Module, classes: LabelClasses, seed: int = 0) -> LabelHead:
    """Give ``model`` a :class:`LabelHead` for ``classes`` over its field's space and
    features (initialised from ``seed``, leaving torch's global random state as it was);
    ValueError for models whose renderer cannot keep sample features."""
    if not getattr(model, "supports_labels", False):
        raise ValueError(f"{type(model).__name__} cannot render labels: use a method marched "
                         "over an occupancy grid (ngp, plenoxels, tensorf, ...) or nerf")
    normalize = getattr(model.field, "normalize", None)
    normalize = copy.deepcopy(normalize) if normalize is not None else \
        BoxNormalizer(model.aabb.detach().cpu())
    gen_state = torch.random.get_rng_state()
    torch.manual_seed(seed + 7919)
    try:
        head = LabelHead(normalize, feature_dim(model), classes)
    finally:
        torch.random.set_rng_state(gen_state)
    model.label_head = head.to(model.aabb.device)
    return head
