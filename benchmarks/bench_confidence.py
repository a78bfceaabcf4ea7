"""Fit and check the calibrated confidences of query answers (thgs.confidence, docs/query.md).

    .venv/bin/python benchmarks/bench_confidence.py --fit-seeds 0 1 2 --report-seeds 5 6 7

Cells are synth-small scenes (seed × Gaussian kind × mask-fault severity × CLIP stand-in, a
``kind/severity/stand-in`` spec such as ``3dgs/0.5/clip-like``), built as in
``bench_selection.py`` (its :class:`Scene`, kept in ``--out``). Every name in a scene's ground
truth (objects, parts, sub-parts) is asked, and 12 phrases naming nothing there. Each selectable
region of levels 1–3 is scored z = (cosine − μ) / σ on centred cosines against the scene's null
(:meth:`thgs.query.FieldQuery.null_model`) and labelled *belongs* when the query names something
in the scene and at least half of the region's Gaussians lie in it; each query's best score is
labelled *present* when the query names something in the scene. Logistic regressions (L2 weight
1e-3 on the slope) are fitted on the fit seeds and printed as the constants to ship; then the
*shipped* constants (thgs.confidence) are checked on the report seeds: expected calibration
error (10 equal-width bins), Brier score (against always predicting the base rate) and AUC, for
regions and for presence, and the share of named queries whose selection (automatic mode) has
3-D IoU ≥ 0.5 against the presence confidence.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.special import expit
from scipy.stats import rankdata

sys.path.insert(0, str(Path(__file__).parent))

from bench_selection import NONSENSE, Scene

from thgs.confidence import presence_confidence, region_confidence
from thgs.eval.ground_truth import read_hierarchy
from thgs.pipeline import FieldConfig
from thgs.query import FieldQuery
from thgs.text import MiniLMEncoder


def records(scene: Scene, spec: str) -> dict[str, list]:
    """Region scores and labels, query best scores and labels, and named queries' 3-D IoU of
    the automatic selection, in query order."""
    regions = scene.regions(spec)
    truth = read_hierarchy(scene.folder / "ground_truth.safetensors")
    engine = FieldQuery(regions, scene.encoder)
    named: dict[str, np.ndarray] = {}
    for level in (1, 2, 3):
        names = truth.level_names(level)
        for name in set(truth.names[level]):
            named[name] = named.get(name, np.zeros(len(names), bool)) | (names == name)
    null = engine.null_model()
    assert null is not None
    rows: dict[str, list] = {"region": [], "belongs": [], "best": [], "present": [], "iou": []}
    for text in [*sorted(named), *NONSENSE]:
        inside = named.get(text)
        best = -np.inf
        for level in (1, 2, 3):
            z = null.score(engine.centred_similarity([text], level)[0])
            sizes = regions.sizes(level)
            for region in np.flatnonzero(regions.seen[level - 1] & (sizes >= engine.min_gaussians)):
                share = (
                    inside[regions.labels[:, level] == region].mean() if inside is not None else 0
                )
                rows["region"].append(z[region])
                rows["belongs"].append(share >= 0.5)
                best = max(best, z[region])
        rows["best"].append(best)
        rows["present"].append(inside is not None)
        if inside is not None:
            selection = engine.select([text])[0]
            overlap = (inside & selection.gaussians).sum() / (inside | selection.gaussians).sum()
            rows["iou"].append(float(overlap))
    return {key: np.asarray(values).tolist() for key, values in rows.items()}


def logistic_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, offset) minimising the mean log loss of σ(slope x + offset) + 1e-3 slope²."""

    def loss(w: np.ndarray) -> float:
        p = np.clip(expit(w[0] * x + w[1]), 1e-12, 1 - 1e-12)
        return float(-(y * np.log(p) + (1 - y) * np.log(1 - p)).mean() + 1e-3 * w[0] ** 2)

    slope, offset = minimize(loss, np.zeros(2), method="BFGS").x
    return float(slope), float(offset)


def calibration_error(p: np.ndarray, y: np.ndarray, bins: int = 10) -> float:
    """Expected calibration error over ``bins`` equal-width bins of p."""
    index = np.minimum((p * bins).astype(int), bins - 1)
    return float(
        sum((index == b).mean() * abs(p[index == b].mean() - y[index == b].mean())
            for b in range(bins) if (index == b).any())
    )  # fmt: skip


def auc(p: np.ndarray, y: np.ndarray) -> float:
    """Area under the ROC curve (rank statistic, ties averaged)."""
    ranks, positives = rankdata(p), y.sum()
    negatives = len(y) - positives
    return float((ranks[y].sum() - positives * (positives + 1) / 2) / (positives * negatives))


def report(name: str, p: np.ndarray, y: np.ndarray) -> None:
    base = ((y.mean() - y) ** 2).mean()
    print(
        f"| {name} | {len(y)} | {y.mean():.3f} | {calibration_error(p, y):.3f} | "
        f"{((p - y) ** 2).mean():.4f} ({base:.4f}) | {auc(p, y):.3f} |"
    )


def cells(specs: list[str], seeds: list[int]) -> list[tuple]:
    """(seed, kind, severity, stand-in) for every seed and ``kind/severity/stand-in`` cell."""
    parsed = [spec.split("/", 2) for spec in specs]
    return [(seed, k, float(s), stand) for seed, (k, s, stand) in itertools.product(seeds, parsed)]


def gather(out: Path, todo: list[tuple]) -> dict[str, np.ndarray]:
    encoder, config = MiniLMEncoder(), FieldConfig.lerf()
    rows: dict[str, list] = {}
    for seed, kind, severity, spec in todo:
        scene = Scene(out, seed, kind, severity, encoder, config)
        for key, values in records(scene, spec).items():
            rows.setdefault(key, []).extend(values)
        print(f"cell seed {seed} {kind} severity {severity:g} {spec}", flush=True)
    return {key: np.array(values) for key, values in rows.items()}


def main() -> None:
    grid = [
        f"{k}/{s:g}/{m}"
        for k, s, m in itertools.product(
            ("2dgs", "3dgs"), (0, 0.5, 1), ("name-perfect", "clip-like")
        )
    ]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fit-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--report-seeds", type=int, nargs="+", default=[5, 6, 7])
    parser.add_argument("--fit-cells", nargs="+", default=grid, help="kind/severity/stand-in")
    parser.add_argument("--report-cells", nargs="+", default=grid, help="kind/severity/stand-in")
    parser.add_argument("--out", type=Path, default=Path("/tmp/thgs-bench-selection"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    fit = gather(args.out, cells(args.fit_cells, args.fit_seeds))
    print("fitted REGION_CALIBRATION =", logistic_fit(fit["region"], fit["belongs"]))
    print("fitted PRESENCE_CALIBRATION =", logistic_fit(fit["best"], fit["present"]))
    held = gather(args.out, cells(args.report_cells, args.report_seeds))
    print("\nshipped constants on the report seeds:\n")
    print("| what | n | positives | ECE | Brier (base rate) | AUC |\n|---|---|---|---|---|---|")
    report("region belongs", region_confidence(held["region"]), held["belongs"])
    report("query present", presence_confidence(held["best"]), held["present"])
    named = presence_confidence(held["best"][held["present"]])
    report("named query: selection IoU ≥ 0.5", named, held["iou"] >= 0.5)


if __name__ == "__main__":
    main()
