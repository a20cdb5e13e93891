"""The encoder's dense outputs as 2D-3D correspondences: which crop pixel shows which model point.

Reading the encoding is the AGM's knowledge (its map's resolution, the mask's logits, points in object radii), so
it lives here and hands the TBM plain `DensePoints`: data flows AGM -> TBM and the solver never sees an `Encoding`.
"""

from __future__ import annotations

import numpy as np
import torch

from axispose_core.agm.denoiser import Encoding
from axispose_core.tbm.dense import DensePoints

MASK_THRESHOLD = 0.5
"""Mask probability from which a cell of the dense map counts as showing the object."""


def dense_correspondences(enc: Encoding, scales: np.ndarray) -> list[DensePoints]:
    """Per crop of an encoding: the dense map's cells that show the object, as crop pixels uv (N,2) (a cell's
    centre: pixel centres at integers), model points X (N,3) in metres (the network's, in object radii, times the
    crop's λ_O in `scales` (B,)) and weights (N,): the mask probability."""
    cells = np.arange(enc.points.shape[-1]) * 2 + 0.5  # a cell of the half-resolution map covers 2 x 2 pixels
    uv = np.stack(np.meshgrid(cells, cells), axis=-1).reshape(-1, 2)
    points = enc.points.detach().float().cpu().numpy().reshape(len(scales), 3, -1).transpose(0, 2, 1)
    prob = torch.sigmoid(enc.mask.detach().float()).cpu().numpy().reshape(len(scales), -1)
    out = []
    for X, p, scale in zip(points, prob, scales, strict=True):
        keep = p > MASK_THRESHOLD
        out.append(DensePoints(uv[keep], X[keep] * float(scale), p[keep]))
    return out
