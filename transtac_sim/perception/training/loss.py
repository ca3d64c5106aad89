"""The detector's loss: CenterNet's focal loss on the heatmap, L1 on offset and size at marker centres, and
the optional correlation term.

Focal loss (alpha = 2, beta = 4), Y the predicted heatmap, T the Gaussian target, N the number of centres:
    L_heat = -1/N sum [T = 1] (1 - Y)^a log Y + [T < 1] (1 - T)^b Y^a log(1 - Y)
Correlation term (the paper's feature consistency among markers of one local cluster), f_i the unit
feature vector (the decoder's last map at marker i's centre cell) and K(i) the ``k`` nearest markers
within ``radius`` cells:
    L_corr = mean_i mean_{j in K(i)} (1 - f_i . f_j)
Total: L_heat + L_offset + 0.1 L_size + lambda_corr L_corr.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.nn import functional as fn


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    pred = torch.sigmoid(logits.float()).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    pos_loss = (torch.log(pred) * (1 - pred) ** 2 * pos).sum()
    neg_loss = (torch.log(1 - pred) * pred**2 * (1 - target) ** 4 * (1 - pos)).sum()
    return -(pos_loss + neg_loss) / pos.sum().clamp(min=1.0)


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return (torch.abs(pred.float() - target) * mask).sum() / (mask.sum() * pred.shape[1]).clamp(min=1.0)


def correlation_term(features: torch.Tensor, centres: list[np.ndarray], k: int = 4, radius_cells: float = 12.0) -> torch.Tensor:
    """L_corr over a batch: ``centres[b]`` (N_b, 2) integer cells (x, y) of image b's markers."""
    terms = []
    for b, c in enumerate(centres):
        if len(c) < 2:
            continue
        f = fn.normalize(features[b, :, c[:, 1], c[:, 0]].float().T, dim=1)  # (N, C)
        dist, idx = cKDTree(c).query(c, k=min(k + 1, len(c)), distance_upper_bound=radius_cells)
        pairs = [(i, j) for i in range(len(c)) for d, j in zip(dist[i, 1:], idx[i, 1:], strict=True) if np.isfinite(d)]
        if pairs:
            a, bb = (torch.as_tensor(x, device=features.device) for x in zip(*pairs, strict=True))
            terms.append((1.0 - (f[a] * f[bb]).sum(1)).mean())
    return torch.stack(terms).mean() if terms else features.sum() * 0.0
