"""The automatic selection against the paper's across scenarios (docs/query.md).

    .venv/bin/python benchmarks/bench_selection.py --seeds 5 6 --out /tmp/selection

For every seed × Gaussian kind (2dgs, 3dgs) × mask-fault severity (0, 0.5, 1) × CLIP-likeness of
the oracle's features (``--context-mixes``, default 0 and 0.5), a synth-small dataset is written
with ``thgs synth`` and its field built with ``thgs build`` (both cached in ``--out``); then,
through the library: LERF-style mIoU under the THGS rule with the automatic selection (``lerf``)
and the paper's (``lerf-paper``), 3D-OVS mIoU (automatic), its ceiling (``3dovs-ceiling``: the
same protocol selecting each class's ground-truth Gaussians, exactly; what no selection of
Gaussians can beat, because a rendered selection's edges never match the ground truth's
pixels exactly), the share of the scene's LERF categories the automatic selection answers and the
share of 12 phrases naming nothing in the scene it abstains on. One JSON line per cell, then a
markdown table of the means over seeds, the mean and the worst cell.
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from thgs import load_scene
from thgs.eval import evaluate_3dovs, evaluate_dataset, find_ground_truth
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.three_dovs import read_3dovs_segmentations
from thgs.field import load_field
from thgs.pipeline import lifted_raster
from thgs.query import FieldQuery, QueryConfig
from thgs.synthetic import is_current_dataset
from thgs.text import load_text_encoder

NONSENSE = (
    "a giraffe", "the ocean", "a fire truck", "snow", "a violin", "a laptop", "a bicycle",
    "a red sports car", "the moon", "a palm tree", "a toothbrush", "an elephant",
)  # fmt: skip
THGS = str(Path(sys.executable).with_name("thgs"))


def scenario(out: Path, seed: int, kind: str, severity: float, mix: float) -> tuple[Path, Path]:
    """The dataset and field of one cell, written with ``thgs synth`` and ``thgs build`` unless
    ``out`` holds them already."""
    dataset = out / f"{kind}-seed{seed}-severity{severity:g}-context{mix:g}"
    field_path = Path(f"{dataset}.thgs")
    if not is_current_dataset(dataset):
        field_path.unlink(missing_ok=True)
        command = [THGS, "synth", "synth-small", str(dataset), "--seed", str(seed), "--kind", kind]
        command += ["--severity", str(severity), "--context-mix", str(mix), "--overwrite"]
        subprocess.run(command, check=True, capture_output=True)
    if not field_path.is_file():
        command = [THGS, "build", str(dataset), "-o", str(field_path)]
        subprocess.run(command, check=True, capture_output=True)
    return dataset, field_path


class GroundTruthSelection:
    """Stands in for a :class:`FieldQuery` in :func:`evaluate_3dovs`: each object class selects
    exactly its ground-truth Gaussians."""

    config = QueryConfig(mode="level")

    def __init__(self, dataset: Path):
        hierarchy = read_hierarchy(dataset / "ground_truth.safetensors")
        self.objects, self.names = hierarchy.labels[:, 3], hierarchy.names[3]

    def selected(self, texts: list[str]) -> np.ndarray:
        """[N, Q] bool: the Gaussians of the objects named ``texts[q]``."""
        ids = [[i for i, name in enumerate(self.names) if name == text] for text in texts]
        return np.stack([np.isin(self.objects, nodes) for nodes in ids], axis=1)


def cell(out: Path, seed: int, kind: str, severity: float, mix: float) -> dict:
    dataset, field_path = scenario(out, seed, kind, severity, mix)
    field, scene = load_field(field_path), load_scene(dataset)
    engine = FieldQuery(field, load_text_encoder(field.space))
    raster = lifted_raster(field)
    report = evaluate_dataset(
        find_ground_truth(dataset),
        engine,
        scene.gaussians,
        scene.cameras,
        protocols=("lerf", "3dovs"),
        raster=raster,
    )
    ceiling = evaluate_3dovs(
        GroundTruthSelection(dataset),  # type: ignore[arg-type]
        scene.gaussians,
        scene.cameras,
        read_3dovs_segmentations(dataset),
        raster=raster,
    )
    named = sorted({i["prompt"] for r in report.results if r.protocol == "lerf" for i in r.items})
    return {
        "seed": seed,
        "kind": kind,
        "severity": severity,
        "context_mix": mix,
        "automatic": report.metric("lerf", "miou"),
        "paper": report.metric("lerf-paper", "miou"),
        "3dovs": report.metric("3dovs", "miou"),
        "3dovs-ceiling": ceiling.metrics["miou"],
        "answered": float(np.mean([not s.empty for s in engine.select(named)])),
        "abstained": float(np.mean([s.empty for s in engine.select(list(NONSENSE))])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[5, 6])
    parser.add_argument("--context-mixes", type=float, nargs="+", default=[0.0, 0.5])
    parser.add_argument("--out", type=Path, default=Path("/tmp/thgs-bench-selection"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    grid = itertools.product(args.seeds, ("2dgs", "3dgs"), (0.0, 0.5, 1.0), args.context_mixes)
    for seed, kind, severity, mix in grid:
        rows.append(cell(args.out, seed, kind, severity, mix))
        print(json.dumps(rows[-1]), flush=True)
    cells: dict[tuple, list[dict]] = {}
    for row in rows:
        cells.setdefault((row["kind"], row["severity"], row["context_mix"]), []).append(row)
    keys = ("automatic", "paper", "3dovs", "3dovs-ceiling", "answered", "abstained")
    print("\n| kind | severity | context mix | " + " | ".join(keys) + " |")
    print("|---|---|---|" + "---|" * len(keys))
    means = []
    for (kind, severity, mix), group in cells.items():
        means.append([float(np.mean([row[key] for row in group])) for key in keys])
        values = " | ".join(f"{value:.3f}" for value in means[-1])
        print(f"| {kind} | {severity:g} | {mix:g} | {values} |")
    table = np.array(means)
    print("| mean | | | " + " | ".join(f"{v:.3f}" for v in table.mean(axis=0)) + " |")
    print("| worst cell | | | " + " | ".join(f"{v:.3f}" for v in table.min(axis=0)) + " |")


if __name__ == "__main__":
    main()
