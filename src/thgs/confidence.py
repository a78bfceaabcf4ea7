"""Calibrated confidence of query answers, against the scene's own distribution (docs/query.md).

Raw cosines and relevancies mean different things in different embedding spaces (CLIP's are
compressed into a narrow band, MiniLM's are not) and in different scenes. Cosines are therefore
read on features centred on the scene's mean feature
(:meth:`thgs.query.FieldQuery.centred_similarity`), and each query against a *null*: how well
the 80 COCO class names (:data:`NULL_PHRASES`, a fixed, generic vocabulary chosen by nobody
here) match the same scene. For every null phrase the best centred cosine over the scene's
candidate regions is taken; their mean μ and standard deviation σ describe how close "some
ordinary thing" gets in this scene and this space. A region's centred cosine with the query
becomes the score ``z = (cosine − μ) / σ``, and two logistic calibrations turn scores into
probabilities:

- **region confidence** ``σ(a_r z + b_r)``: the probability that the region belongs to what was
  asked (most of its Gaussians lie in it);
- **presence confidence** ``σ(a_p z_best + b_p)``, with ``z_best`` the best region's score: the
  probability that the scene holds what the query names at all.

Both pairs of constants were fitted (logistic regression, L2 weight 1e-3) on synth-small seeds
0–2 with name-perfect and CLIP-like stand-in features and are reported on seeds 5–7
(``benchmarks/bench_confidence.py``; docs/query.md). They are measured on the MiniLM stand-in
for CLIP; with real CLIP the scores are the same kind of number (distance from the scene's null
in units of its spread) but the calibration is not measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from thgs.errors import InputError

__all__ = [
    "NULL_PHRASES",
    "PRESENCE_CALIBRATION",
    "REGION_CALIBRATION",
    "NullModel",
    "presence_confidence",
    "region_confidence",
]

NULL_PHRASES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich",
    "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote",
    "keyboard", "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book",
    "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip
"""The 80 COCO class names: the generic vocabulary each scene's null is measured with."""

REGION_CALIBRATION = (1.50, -3.19)
"""(slope, offset) of the region confidence: σ(slope · z + offset)."""

PRESENCE_CALIBRATION = (3.47, -5.01)
"""(slope, offset) of the presence confidence: σ(slope · z_best + offset)."""


@dataclass(frozen=True)
class NullModel:
    """How well generic phrases match one scene.

    Attributes:
        mean: μ, the mean over the null phrases of each phrase's best cosine over the regions.
        std: σ, their standard deviation (> 0).
    """

    mean: float
    std: float

    @classmethod
    def from_similarities(cls, cosines: np.ndarray, source: str = "null phrases") -> NullModel:
        """The null of a scene from ``cosines``: [P, C] cosine of each of P ≥ 2 null phrases with
        each of the C candidate regions (C ≥ 1).

        Raises:
            InputError: fewer than 2 phrases or no region, or every phrase scoring the same.
        """
        cosines = np.asarray(cosines, dtype=np.float64)
        if cosines.ndim != 2 or cosines.shape[0] < 2 or cosines.shape[1] < 1:
            raise InputError(
                source, f"needs [P ≥ 2, C ≥ 1] cosines, got shape {list(cosines.shape)}"
            )
        best = cosines.max(axis=1)
        std = float(best.std())
        if not std > 0:
            raise InputError(source, "every null phrase matches the scene equally well")
        return cls(float(best.mean()), std)

    def score(self, cosines: np.ndarray) -> np.ndarray:
        """z = (cosine − μ) / σ, elementwise (same shape as ``cosines``)."""
        return (np.asarray(cosines, dtype=np.float64) - self.mean) / self.std


def region_confidence(scores: np.ndarray) -> np.ndarray:
    """The probability that each region belongs to what was asked, from its score ``z``
    (:meth:`NullModel.score`); same shape as ``scores``, values in (0, 1)."""
    slope, offset = REGION_CALIBRATION
    return expit(slope * np.asarray(scores, dtype=np.float64) + offset)


def presence_confidence(best_scores: np.ndarray) -> np.ndarray:
    """The probability that the scene holds what each query names, from its best region's score
    ``z_best``; same shape as ``best_scores``, values in (0, 1)."""
    slope, offset = PRESENCE_CALIBRATION
    return expit(slope * np.asarray(best_scores, dtype=np.float64) + offset)
