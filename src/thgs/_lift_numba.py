"""The latent method's decision compiled for the CPU (:mod:`thgs.lift`'s fast path).

Per seen Gaussian and level the splatted code sum is ``y = Σ_t W_t·Y_t + β·W_bg·Y_bg`` over the
masks t it touches (``W_bg``: its weight on pixels without a mask); its label is the most similar
code among all the level's masks and the background, if that cosine exceeds τ. Scanning every
mask for every Gaussian is what makes the decision slow, and is rarely needed: for a mask t' the
Gaussian does not touch,

    cos(y, Y_t') = (Σ_t W_t Y_t·Y_t' + β W_bg Y_bg·Y_t') / |y| ≤ (Σ_t W_t M_t + β |W_bg| M_bg) / |y|

with ``M_t = max_{t' ≠ t} Y_t·Y_t'`` and ``M_bg = max_t' |Y_bg·Y_t'|``. When that bound is at most
τ or below the best touched (or background) cosine, no untouched mask can win or pass τ, and the
answer is the same as the full scan; otherwise the Gaussian's sum is compared with every code.
The result equals :func:`thgs.lift._latent_labels` (the torch version) up to the rounding of the
cosines (tested).
"""

from __future__ import annotations

import math

import numba
import numpy as np

_MARGIN = 1e-12
"""Added to the bound so that rounding never skips a scan the exact bound would need."""


@numba.njit(nogil=True, cache=True)
def latent_labels_kernel(
    n, rows, levels, labels, weights, totals, codes, background, present, scale, threshold
):  # pragma: no cover - compiled
    """[n, L] int64 labels (−1 none) from per-mask weights sorted by (row, level, label).

    Args:
        n: seen Gaussians; rows, levels, labels, weights: [P] the per-mask weights.
        totals: [n] ``Σ_x w(x)``; codes: [F, D] unit mask codes; background: [L, D] unit codes.
        present: [L, F] bool, masks occurring at each level; scale: β; threshold: τ.
    """
    level_count, dim = background.shape
    out = np.full((n, level_count), -1, dtype=np.int64)
    # per level: the masks present, the bound of each code against the others, the background's
    ids_of = []
    bound_of = np.full((level_count, codes.shape[0]), -math.inf)
    background_dots = np.zeros((level_count, codes.shape[0]))
    background_bound = np.zeros(level_count)
    for level in range(level_count):
        ids = np.flatnonzero(present[level])
        ids_of.append(ids)
        for a in range(len(ids)):
            for b in range(len(ids)):
                if a != b:
                    dot = 0.0
                    for d in range(dim):
                        dot += codes[ids[a], d] * codes[ids[b], d]
                    bound_of[level, ids[a]] = max(bound_of[level, ids[a]], dot)
            dot = 0.0
            for d in range(dim):
                dot += background[level, d] * codes[ids[a], d]
            background_dots[level, ids[a]] = dot
            background_bound[level] = max(background_bound[level], abs(dot))
    y = np.empty(dim)
    p = 0
    total_entries = rows.shape[0]
    while p < total_entries:
        row, level = rows[p], levels[p]
        end = p
        while end < total_entries and rows[end] == row and levels[end] == level:
            end += 1
        ids = ids_of[level]
        if len(ids) == 0:
            p = end
            continue
        explicit, norm, reach, best_cosine, best = True, 1.0, 0.0, 0.0, -1
        if end == p + 1:
            # one mask: y = W·Y_t + b·Y_bg, everything from W, b and g = Y_t·Y_bg
            t, w = labels[p], weights[p]
            rest = totals[row] - w
            b = scale * rest
            g = background_dots[level, t]
            norm = math.sqrt(max(w * w + b * b + 2.0 * w * b * g, 0.0))
            if norm == 0.0:
                p = end
                continue
            best_cosine, best = (w * g + b) / norm, -1
            cosine = (w + b * g) / norm
            if cosine >= best_cosine:
                best_cosine, best = cosine, t
            reach = abs(b) * background_bound[level] + w * bound_of[level, t]
            explicit = False
        bound = math.inf if explicit else reach / norm + _MARGIN
        if explicit or (bound > threshold and bound >= best_cosine):
            for d in range(dim):
                y[d] = 0.0
            labelled = 0.0
            for q in range(p, end):
                w = weights[q]
                labelled += w
                for d in range(dim):
                    y[d] += w * codes[labels[q], d]
            rest = totals[row] - labelled
            for d in range(dim):
                y[d] += scale * rest * background[level, d]
            norm = 0.0
            for d in range(dim):
                norm += y[d] * y[d]
            norm = math.sqrt(norm)
            if norm == 0.0:
                p = end
                continue
            # the background, then the touched masks in ascending order; a mask wins ties
            # (with the background, and the first of equal masks), as in the full scan
            best_cosine = 0.0
            for d in range(dim):
                best_cosine += y[d] * background[level, d]
            best_cosine /= norm
            best = -1
            reach = scale * abs(rest) * background_bound[level]
            for q in range(p, end):
                reach += weights[q] * bound_of[level, labels[q]]
                dot = 0.0
                for d in range(dim):
                    dot += y[d] * codes[labels[q], d]
                cosine = dot / norm
                if cosine > best_cosine or (cosine == best_cosine and best < 0):
                    best_cosine, best = cosine, labels[q]
        reach = reach / norm + _MARGIN
        if reach > threshold and reach >= best_cosine:
            # an untouched mask might win or pass τ: every code of the level, as the paper
            background_cosine = 0.0
            for d in range(dim):
                background_cosine += y[d] * background[level, d]
            best_cosine, best = background_cosine / norm, -1
            for t in ids:
                dot = 0.0
                for d in range(dim):
                    dot += y[d] * codes[t, d]
                cosine = dot / norm
                if cosine > best_cosine or (cosine == best_cosine and best < 0):
                    best_cosine, best = cosine, t
        if best >= 0 and best_cosine > threshold:
            out[row, level] = best
        p = end
    return out
