"""The estimator's stages that run no network, over a batch of crops: cutting the crops (`crop_batch`, `CropBatch`),
the TBM's poses of each box's samples with the encoder's depth fused in and their consensus (`solve_samples`), and
the final pose from the encoder's dense points (`fuse_samples`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from axispose_core.agm.correspondences import dense_correspondences
from axispose_core.agm.denoiser import Encoding
from axispose_core.camera import InstanceCrop, instance_crop, validate_intrinsics
from axispose_core.consensus import Consensus, consensus
from axispose_core.pose_estimate import PoseEstimate
from axispose_core.tbm.backproject import backproject_readings
from axispose_core.tbm.dense import DenseFusion, fuse_pose
from axispose_core.tbm.keypoints import AxisKeypoints


def crop_batch(
    image_rgb: np.ndarray, K: np.ndarray, boxes: list[tuple[int, tuple[float, float, float, float]]], known: dict, size: int, pad: float
) -> tuple[list[InstanceCrop], torch.Tensor]:
    """Check K and that every box's object is `known`, then cut the boxes' crops and their (B,3,S,S) uint8 batch
    (the network normalises it): one place, so the estimator and the direct baseline read an image the same way."""
    K = validate_intrinsics(K)
    unknown = [o for o, _ in boxes if o not in known]
    if unknown:
        raise ValueError(f"objects {unknown} are not in this checkpoint (it knows {sorted(known)})")
    cuts = [instance_crop(image_rgb, K, box, size, pad=pad) for _, box in boxes]
    if not cuts:
        return cuts, torch.zeros((0, 3, size, size), dtype=torch.uint8)
    return cuts, torch.from_numpy(np.stack([c.patch for c in cuts])).permute(0, 3, 1, 2)


def fuse_depth(t: np.ndarray, z_head: float, weight: float) -> np.ndarray:
    """The TBM's translation `t` moved along its ray to the fused depth: the geometric mean of its depth and the
    encoder's `z_head`, weighted `weight` (head_depth_weight) for the encoder's; both scale with λ_O, so the
    result does too."""
    if weight <= 0 or t[2] <= 0:
        return t
    return t * float(np.exp(weight * (np.log(z_head) - np.log(t[2]))))


@dataclass(frozen=True)
class CropBatch:
    """The crop stage's output, which the later stages share: per box its crop, embedding row and axis lengths (B,3);
    per sample (each box's `hypotheses` in a row) the intrinsics and lengths its keypoints are solved with."""

    boxes: list[tuple[int, tuple[float, float, float, float]]]
    cuts: list[InstanceCrop]
    pixels: torch.Tensor
    """(B,3,S,S) uint8: the network normalises it."""
    objects: torch.Tensor
    lengths: np.ndarray
    hypotheses: int
    K_rows: np.ndarray
    length_rows: np.ndarray


@dataclass(frozen=True)
class Solved:
    """One box after the solve stage: the encoder's depth, its samples' poses (sample row, R, t with the fused depth),
    why the others failed, and the poses' consensus (None: no sample gave one)."""

    head_depth: float
    poses: list[tuple[int, np.ndarray, np.ndarray]]
    reasons: list[str]
    consensus: Consensus | None


def solve_samples(batch: CropBatch, readings: list[AxisKeypoints], enc: Encoding, head_depth: Callable[[float, np.ndarray, float], float],
                  weight: float) -> list[Solved]:  # fmt: skip
    """The TBM's pose of every sample (all boxes' in one refinement), its depth fused with the encoder's
    (`head_depth_weight`), and per box the consensus of the samples that gave one."""
    log_depth = enc.log_depth.detach().float().cpu().numpy()  # guided sampling runs outside inference mode
    results = backproject_readings(batch.K_rows, readings, batch.length_rows)
    k, out = batch.hypotheses, []
    for i, (cut, L) in enumerate(zip(batch.cuts, batch.lengths, strict=True)):
        z_head = head_depth(float(log_depth[i]), cut.K_patch, float(L[0]))
        poses, reasons = [], []
        for row in range(i * k, (i + 1) * k):
            res = results[row]
            if res is not None and res.ok:
                poses.append((row, res.R, fuse_depth(res.t, z_head, weight)))
            else:
                reasons.append(readings[row].reason if res is None else res.reason)
        agreed = consensus(np.stack([p[1] for p in poses]), np.stack([p[2] for p in poses]), float(L.max())) if poses else None
        out.append(Solved(z_head, poses, reasons, agreed))
    return out


def fuse_samples(batch: CropBatch, enc: Encoding, images: torch.Tensor, solved: list[Solved], fusion: DenseFusion) -> list[PoseEstimate]:
    """Each box's pose from the encoder's dense points with its consensus and depth as priors (`dense_fusion`;
    points 0: the consensus as it is) and its covariance; a box no sample posed says why."""
    dense = dense_correspondences(enc, batch.lengths[:, 0]) if fusion.points > 0 else None
    out = []
    for i, ((obj_id, _), cut, s) in enumerate(zip(batch.boxes, batch.cuts, solved, strict=True)):
        pick = dict(obj_id=obj_id, K_patch=cut.K_patch, center=cut.center, side=cut.side, samples=batch.hypotheses,
                    samples_ok=len(s.poses), head_depth=s.head_depth)  # fmt: skip
        c = s.consensus
        if c is None:
            axis_image = images[i * batch.hypotheses].permute(1, 2, 0).cpu().numpy()
            out.append(PoseEstimate(R=np.eye(3), t=np.zeros(3), ok=False, reason=s.reasons[0], axis_image=axis_image, **pick))
            continue
        many = len(s.poses) > 1
        axis_image = images[s.poses[c.medoid][0]].permute(1, 2, 0).cpu().numpy()
        spread = dict(spread_deg=c.spread_deg, spread_m=c.spread_m) if many else {}
        R, t, cov, fit = c.R, c.t, (c.covariance if many else None), None
        if dense is not None and (fused := fuse_pose(cut.K_patch, R, t, dense[i], s.head_depth, fusion)) is not None:
            # The law of total covariance: the fusion's own (given the consensus) plus the samples' scatter about it.
            R, t, cov, fit = fused.R, fused.t, fused.covariance + (c.scatter if many else 0.0), fused.covariance
        out.append(PoseEstimate(R=R, t=t, ok=True, reason="", axis_image=axis_image, covariance=cov, fit_covariance=fit, **pick,
                                **spread))  # fmt: skip
    return out
