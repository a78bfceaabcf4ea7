"""Synthetic benchmark scenes with exact hierarchy ground truth and SAM-like oracle guidance.

Usage::

    from thgs.synthetic import generate_scene, preset, write_dataset
    from thgs.text import MiniLMEncoder

    scene = generate_scene(preset("synth-small", seed=1))
    write_dataset("out/synth-small", scene, MiniLMEncoder())

:func:`write_opengaussian_scannet` lays a dataset out as OpenGaussian's ScanNet scenes, and
:func:`write_openhype_scannetpp` as a scene of OpenHype's ScanNet++ benchmark
(:mod:`thgs.synthetic.layouts`). See docs/synthetic.md.
"""

from thgs.synthetic.dataset import (
    DATASET_VERSION,
    DatasetConfig,
    DatasetSummary,
    check_dataset_output,
    evaluation_views,
    is_current_dataset,
    label_categories,
    render_view,
    write_dataset,
)
from thgs.synthetic.layouts import (
    write_3dovs,
    write_langsplat_lerf,
    write_opengaussian_scannet,
    write_openhype_scannetpp,
)
from thgs.synthetic.oracle import (
    CLIP_GRID,
    STAND_INS,
    OracleConfig,
    oracle_guidance,
    stand_in,
    stand_in_spec,
)
from thgs.synthetic.sam_masks import FaultRates, LevelMasks
from thgs.synthetic.scene import PRESETS, SceneConfig, SyntheticScene, generate_scene, preset

__all__ = [
    "CLIP_GRID",
    "DATASET_VERSION",
    "PRESETS",
    "STAND_INS",
    "DatasetConfig",
    "DatasetSummary",
    "FaultRates",
    "LevelMasks",
    "OracleConfig",
    "SceneConfig",
    "SyntheticScene",
    "check_dataset_output",
    "evaluation_views",
    "generate_scene",
    "is_current_dataset",
    "label_categories",
    "oracle_guidance",
    "preset",
    "render_view",
    "stand_in",
    "stand_in_spec",
    "write_3dovs",
    "write_dataset",
    "write_langsplat_lerf",
    "write_opengaussian_scannet",
    "write_openhype_scannetpp",
]
