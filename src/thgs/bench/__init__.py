"""``thgs bench``: time, memory and quality of the method and its ablations in one run.

For each synthetic preset (:func:`thgs.synthetic.cache.synthetic_dataset`, cached), the field is
built with the LERF preset ("full") and with each variant of :data:`VARIANTS`: the paper's Table 3
ablations (no edge reweighting, no depth decay, instance level only, no progressive merging),
the lifting and reweighting alternatives (exact lifting, absolute offsets) and the authors' code
as a whole. Every variant is scored by every protocol the dataset has ground truth for
(:func:`thgs.eval.evaluate_dataset`: LERF-OVS under the THGS, LangSplat and OpenGaussian rules,
3D-OVS, ScanNet-style classes, per-level agreement with the hierarchy).

Modules: :mod:`thgs.bench.variants` (what is built), :mod:`thgs.bench.run` (building, timing and
scoring), :mod:`thgs.bench.report` (the tables, the plot and the files).
"""

from thgs.bench.report import BenchReport, VariantRun, require_matplotlib, write_bench
from thgs.bench.run import BenchConfig, default_presets, measured, run_bench
from thgs.bench.variants import ORDERINGS, VARIANTS

__all__ = [
    "ORDERINGS",
    "VARIANTS",
    "BenchConfig",
    "BenchReport",
    "VariantRun",
    "default_presets",
    "measured",
    "require_matplotlib",
    "run_bench",
    "write_bench",
]
