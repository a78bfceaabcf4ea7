"""What every rasterization backend returns (the same fields, whichever computed them)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["LabelWeights", "RenderOutput", "SplatBackOutput"]


@dataclass(frozen=True, eq=False)
class RenderOutput:
    """One rendered view. With ``w_k(x) = α_k(x) · T_k(x)`` the blending weight of Gaussian k.

    Attributes:
        image: [H, W, C] ``Σ_k w_k(x) · features[k]``, in the features' dtype.
        alpha: [H, W] accumulated opacity ``Σ_k w_k(x)`` in [0, 1].
        depth: [H, W] ``Σ_k w_k z_k / Σ_k w_k`` with z_k the camera-space depth of Gaussian k's
            centre (for 2DGS too, not the ray–surfel intersection); 0 where alpha is 0.
        max_id: [H, W] int64 index of the Gaussian with the largest ``w_k(x)`` (the nearest on
            ties), −1 where no Gaussian contributes.
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    max_id: Tensor


@dataclass(frozen=True, eq=False)
class SplatBackOutput:
    """Per-Gaussian sums of a pixel map over the pixels each Gaussian contributes to.

    Only pixels inside the mask are summed; all pixels still composite (occlusion is unchanged).

    Attributes:
        feature_sums: [N, C] ``Σ_x w_k(x) · F(x)``.
        weight_sums: [N] ``Σ_x w_k(x)``.
        max_weights: [N] ``max_x w_k(x)`` (0 where the Gaussian contributes to no pixel).
        pixel_counts: [N] int64 number of pixels with ``w_k(x) > 0``.
        depths: [N] camera-space z of each centre (scene units; ≤ 0 behind the camera).
        centers: [N, 2] projected centres in pixels (pixel (u, v) is centred at (u+0.5, v+0.5));
            meaningless where depth ≤ 0.
    """

    feature_sums: Tensor
    weight_sums: Tensor
    max_weights: Tensor
    pixel_counts: Tensor
    depths: Tensor
    centers: Tensor


@dataclass(frozen=True, eq=False)
class LabelWeights:
    """How much of each Gaussian's blending weight falls on each label of integer label maps.

    Sparse: one row per (Gaussian, level, label) with a positive weight, sorted by Gaussian, then
    level, then label. Every tensor is on the Gaussians' device; weights are in the backend's
    compute dtype (float64 on the CPU).

    Attributes:
        gaussians: [P] int64 Gaussian index.
        levels: [P] int64 level (first axis of the label maps).
        labels: [P] int64 label.
        weights: [P] ``Σ_{x: label_level(x) = label} w_g(x)``.
        weight_sums: [N] ``Σ_x w_g(x)`` over all pixels, labelled or not.
        max_weights: [N] ``max_x w_g(x)`` (0 where the Gaussian contributes to no pixel).
        depths: [N] camera-space z of each centre (scene units).
    """

    gaussians: Tensor
    levels: Tensor
    labels: Tensor
    weights: Tensor
    weight_sums: Tensor
    max_weights: Tensor
    depths: Tensor
