"""The automatic selection against the paper's, across mask faults and CLIP stand-ins
(docs/query.md, docs/synthetic.md).

    .venv/bin/python benchmarks/bench_selection.py --seeds 5 6 7 8 9 --out /tmp/selection

Every seed × Gaussian kind (2dgs, 3dgs) × mask-fault severity (0, 0.5, 1) is one scene: a
synth-small dataset written once (name-perfect features;
``thgs.synthetic.cache.synthetic_dataset``, cached in ``--out``), lifted, partitioned and merged
once. Each stand-in of ``--stand-ins`` (``thgs.synthetic.stand_in`` specs; default name-perfect,
the CLIP grid around ``clip-like`` and the older ``context_mix`` at 0.8 as a stress case) then
gets its oracle features made again with the very same masks, its region features computed and
its repeated parts grouped: the field that
``thgs synth --stand-in SPEC`` + ``thgs build`` give (checked by tests/test_stand_in.py).
Each such field is kept in ``--out`` with the settings that built it and rebuilt when they differ.

Scored through the library: LERF-style mIoU under the THGS rule with the automatic selection
(``lerf``) and the paper's (``lerf-paper``), the same split into objects and into parts and
sub-parts, 3D-OVS mIoU (automatic and the paper's rule), its ceiling (``3dovs-ceiling``: the
same protocol selecting each class's ground-truth Gaussians exactly; no selection of Gaussians
can beat it), the share of the scene's LERF categories the automatic selection answers and the
share of 12 phrases naming nothing in the scene it abstains on. One JSON line per scene and
stand-in, then per stand-in a markdown table of the means over seeds, the mean and the worst
cell.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from thgs import load_scene
from thgs.eval import evaluate_3dovs, evaluate_dataset, find_ground_truth
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.three_dovs import read_3dovs_segmentations
from thgs.guidance import load_guidance
from thgs.hierarchy import gaussian_neighbors
from thgs.hierarchy.levels import RegionLevels
from thgs.pipeline import FieldConfig, MergedLevels, describe_levels, lift_scene, merge_lifted
from thgs.query import FieldQuery, QueryConfig, Regions
from thgs.synthetic import generate_scene, preset, render_view
from thgs.synthetic import oracle as oracle_module
from thgs.synthetic.cache import synthetic_dataset
from thgs.synthetic.dataset import DatasetConfig
from thgs.synthetic.oracle import CLIP_GRID, OracleConfig, oracle_guidance, stand_in_spec
from thgs.text import MiniLMEncoder

NONSENSE = (
    "a giraffe", "the ocean", "a fire truck", "snow", "a violin", "a laptop", "a bicycle",
    "a red sports car", "the moon", "a palm tree", "a toothbrush", "an elephant",
)  # fmt: skip
STAND_INS = ("name-perfect", *CLIP_GRID, "name-perfect:context_mix=0.8")
KINDS = ("2dgs", "3dgs")
SEVERITIES = (0.0, 0.5, 1.0)


class Scene:
    """One seed × kind × severity: its dataset, lift and merged levels, computed once."""

    def __init__(
        self, out: Path, seed: int, kind: str, severity: float, encoder, config, size=(None, None)
    ):
        self.seed, self.kind, self.severity = seed, kind, severity
        self.encoder, self.config, self.size = encoder, config, size
        self.folder, _ = synthetic_dataset(
            out, "synth-small", seed, *size, encoder, kind=kind, severity=severity
        )
        self.scene = load_scene(self.folder)
        self.guidance = load_guidance(self.folder / "language_features", self.scene.cameras)
        self.cache = out / "fields" / self.folder.name
        self.lifts = out / "lifts"
        self._lifted = self._merged = self._views = None

    @property
    def lifted(self):
        if self._lifted is None:
            lift = self.config.superpoints.lift
            self._lifted = lift_scene(self.scene, self.guidance, lift, cache=self.lifts)
        return self._lifted

    @property
    def merged(self) -> MergedLevels:
        """The merged levels, kept in the bench folder with the settings that made them."""
        if self._merged is None:
            path = self.cache / "merged.npz"
            digest = _digest({"field": self.config.to_json()}, code=False)
            stored = np.load(path) if path.is_file() else None
            if stored is not None and str(stored["settings"]) == digest:
                neighbors = gaussian_neighbors(self.scene.gaussians, self.config.merge.neighbors)
                levels = RegionLevels.from_labels(stored["labels"])
                self._merged = MergedLevels(levels, neighbors, {})
            else:
                self._merged = merge_lifted(self.lifted, self.config)
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez(path, labels=self._merged.levels.labels, settings=digest)
        return self._merged

    def guidance_for(self, oracle: OracleConfig) -> list:
        """The dataset's guidance with the features ``oracle`` gives its masks (the masks
        themselves are the dataset's: they do not depend on the stand-in)."""
        if self._views is None:  # the hierarchy and each view's max-weight ids, once
            sizes = dict(zip(("gaussians", "views"), self.size))
            overrides = {key: value for key, value in sizes.items() if value is not None}
            synthetic = generate_scene(
                preset("synth-small", seed=self.seed, kind=self.kind, **overrides)
            )
            background = DatasetConfig().background
            max_ids = [render_view(synthetic, i, background)[1] for i in range(len(self.guidance))]
            self._views = (synthetic.hierarchy, max_ids)
        hierarchy, max_ids = self._views
        views = []
        for index, (stored, max_id) in enumerate(zip(self.guidance, max_ids)):
            made = oracle_guidance(stored.stem, max_id, hierarchy, self.encoder, oracle, index)
            if not np.array_equal(made.segments, stored.segments):
                raise RuntimeError(f"{self.folder}: the masks of {stored.stem} differ")
            views.append(made)
        return views

    def regions(self, spec: str, rebuild: bool = False) -> Regions:
        """The regions and features of this scene's field with the stand-in ``spec``."""
        oracle = OracleConfig(severity=self.severity, seed=self.seed).with_stand_in(spec)
        digest = _digest({"field": self.config.to_json(), "oracle": oracle.stand_in})
        path = self.cache / f"{stand_in_spec(oracle).replace(':', '-')}.npz"
        if path.is_file() and not rebuild:
            stored = np.load(path)
            if str(stored["settings"]) == digest:
                levels = RegionLevels.from_labels(stored["labels"])
                return Regions(
                    levels,
                    tuple(stored[f"features{k}"] for k in (1, 2, 3)),
                    tuple(stored[f"seen{k}"] for k in (1, 2, 3)),
                    self.encoder.space,
                    self.config.merge.min_region_gaussians,
                )
        guidance = self.guidance if spec == "name-perfect" else self.guidance_for(oracle)
        built = describe_levels(self.merged, self.lifted, guidance, self.config)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f"features{k}": built.features[k - 1] for k in (1, 2, 3)}
        arrays.update({f"seen{k}": built.seen[k - 1] for k in (1, 2, 3)})
        np.savez(path, labels=built.levels.labels, settings=digest, **arrays)
        return Regions(
            built.levels,
            built.features,
            built.seen,
            self.encoder.space,
            self.config.merge.min_region_gaussians,
        )


def _digest(settings: dict, code: bool = True) -> str:
    """The settings' fingerprint, with ``code`` the stand-in's code's too: what a kept result
    was made with (the merged levels depend on the dataset's masks, not on that code)."""
    source = Path(oracle_module.__file__).read_bytes() if code else b""
    text = json.dumps(settings, sort_keys=True).encode() + source
    return hashlib.sha256(text).hexdigest()[:16]


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


def _split(result, objects: set[str]) -> tuple[float, float]:
    """Mean IoU of a LERF result's object prompts and of its part / sub-part prompts, averaged
    per frame then over frames, as the protocol's own mIoU."""
    means = []
    for wanted in (True, False):
        frames: dict[str, list[float]] = {}
        for item in result.items:
            if (item["prompt"] in objects) == wanted:
                frames.setdefault(item["frame"], []).append(item["iou"])
        means.append(float(np.mean([np.mean(v) for v in frames.values()])) if frames else np.nan)
    return means[0], means[1]


def score(scene: Scene, regions: Regions, query: QueryConfig = QueryConfig()) -> dict:
    """Every number of the module docstring for one field."""
    engine = FieldQuery(regions, scene.encoder, query)
    raster = scene.config.superpoints.lift.raster
    report = evaluate_dataset(
        find_ground_truth(scene.folder),
        engine,
        scene.scene.gaussians,
        scene.scene.cameras,
        protocols=("lerf", "3dovs"),
        raster=raster,
    )
    segmentations = read_3dovs_segmentations(scene.folder)
    ceiling = evaluate_3dovs(
        GroundTruthSelection(scene.folder),  # type: ignore[arg-type]
        scene.scene.gaussians,
        scene.scene.cameras,
        segmentations,
        raster=raster,
    )
    paper_3dovs = evaluate_3dovs(
        engine.using(mode="paper", levels=None),
        scene.scene.gaussians,
        scene.scene.cameras,
        segmentations,
        raster=raster,
    )
    results = {result.protocol: result for result in report.results}
    objects = set(read_hierarchy(scene.folder / "ground_truth.safetensors").names[3])
    named = sorted({item["prompt"] for item in results["lerf"].items})
    auto_objects, auto_parts = _split(results["lerf"], objects)
    paper_objects, paper_parts = _split(results["lerf-paper"], objects)
    return {
        "automatic": report.metric("lerf", "miou"),
        "paper": report.metric("lerf-paper", "miou"),
        "automatic objects": auto_objects,
        "automatic parts": auto_parts,
        "paper objects": paper_objects,
        "paper parts": paper_parts,
        "3dovs": report.metric("3dovs", "miou"),
        "3dovs paper": paper_3dovs.metrics["miou"],
        "3dovs-ceiling": ceiling.metrics["miou"],
        "answered": float(np.mean([not s.empty for s in engine.select(named)])),
        "abstained": float(np.mean([s.empty for s in engine.select(list(NONSENSE))])),
    }


COLUMNS = (
    "automatic", "paper", "automatic parts", "paper parts", "3dovs", "3dovs paper",
    "3dovs-ceiling", "answered", "abstained",
)  # fmt: skip


def table(rows: list[dict], spec: str) -> str:
    """The markdown table of one stand-in: means over seeds per kind × severity, the mean and
    the worst cell."""
    cells: dict[tuple, list[dict]] = {}
    for row in rows:
        if row["stand_in"] == spec:
            cells.setdefault((row["kind"], row["severity"]), []).append(row)
    lines = [f"\nstand-in {spec}\n", "| kind | severity | " + " | ".join(COLUMNS) + " |"]
    lines.append("|---|---|" + "---|" * len(COLUMNS))
    means = []
    for (kind, severity), group in cells.items():
        means.append([float(np.nanmean([row[key] for row in group])) for key in COLUMNS])
        values = " | ".join(f"{v:.3f}" for v in means[-1])
        lines.append(f"| {kind} | {severity:g} | {values} |")
    values = np.array(means)
    lines.append("| **mean** | | " + " | ".join(f"{v:.3f}" for v in values.mean(axis=0)) + " |")
    lines.append("| worst cell | | " + " | ".join(f"{v:.3f}" for v in values.min(axis=0)) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[5, 6])
    parser.add_argument("--kinds", nargs="+", default=list(KINDS))
    parser.add_argument("--severities", type=float, nargs="+", default=list(SEVERITIES))
    parser.add_argument("--stand-ins", nargs="+", default=list(STAND_INS))
    parser.add_argument("--out", type=Path, default=Path("/tmp/thgs-bench-selection"))
    parser.add_argument("--rebuild", action="store_true", help="ignore the fields kept in --out")
    args = parser.parse_args()
    for spec in args.stand_ins:
        OracleConfig().with_stand_in(spec)  # a bad spec fails before any work
    args.out.mkdir(parents=True, exist_ok=True)
    encoder, config = MiniLMEncoder(), FieldConfig.lerf()
    rows = []
    for seed, kind, severity in itertools.product(args.seeds, args.kinds, args.severities):
        scene = Scene(args.out, seed, kind, severity, encoder, config)
        for spec in args.stand_ins:
            row = {"seed": seed, "kind": kind, "severity": severity, "stand_in": spec}
            row.update(score(scene, scene.regions(spec, args.rebuild)))
            rows.append(row)
            print(json.dumps(row), flush=True)
    for spec in args.stand_ins:
        print(table(rows, spec))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
