"""Guidance for a splat's virtual views: SAM and CLIP on the renders, or, for a synthetic scene,
the oracle from its ground truth.

- :class:`ModelGuidance`: the renders go through ``thgs preprocess``'s models and settings
  (:func:`thgs.guidance.preprocess.preprocess_images`), resuming as it does;
- :class:`OracleGuidance`: a dataset written by ``thgs synth`` knows every Gaussian's sub-part,
  part and object, so the oracle makes SAM-like masks and CLIP-like features for any camera
  (:func:`thgs.synthetic.oracle.oracle_guidance`, with the dataset's own oracle settings) — the
  whole splat-only path scored against exact answers.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from thgs.errors import InputError
from thgs.guidance.preprocess.generator import MaskGeneratorConfig
from thgs.render import RasterConfig
from thgs.scene import Gaussians
from thgs.splat_views.folder import ViewsFolder, render_views
from thgs.text import LANGSPLAT_SPACE

__all__ = [
    "GuidanceSource",
    "ModelGuidance",
    "OracleGuidance",
    "make_views_guidance",
    "read_dataset_oracle",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class ModelGuidance:
    """SAM masks and CLIP features of the renders (``thgs preprocess``'s models and settings).

    Attributes:
        sam: SAM or SAM 2 in Hugging Face format: a local folder or a cached model id.
        clip: the CLIP model, likewise.
        space: the features' embedding space when ``clip`` is a folder (see ``thgs
            preprocess``).
        device: torch device of the models.
        dtype: their precision (``"float32"``, ``"bfloat16"``, ``"float16"``).
        masks: SAM's automatic mask generator settings.
    """

    sam: str = "facebook/sam-vit-huge"
    clip: str = LANGSPLAT_SPACE
    space: str | None = None
    device: str = "cpu"
    dtype: str = "float32"
    masks: MaskGeneratorConfig = field(default_factory=MaskGeneratorConfig)


@dataclass(frozen=True)
class OracleGuidance:
    """The oracle's masks and features from a synthetic dataset's ground truth.

    Attributes:
        dataset: a folder ``thgs synth`` wrote (``synthetic.json``,
            ``ground_truth.safetensors``); its oracle settings and embedding space are used.
    """

    dataset: Path


GuidanceSource = ModelGuidance | OracleGuidance
"""Where a views folder's guidance comes from."""


def read_dataset_oracle(dataset: str | os.PathLike[str]):
    """A synthetic dataset's oracle settings and embedding space: ``(OracleConfig, space)``.

    Raises:
        InputError: naming the file, when ``synthetic.json`` is missing, unreadable or not a
            thgs synthetic record.
    """
    from thgs.synthetic.oracle import OracleConfig
    from thgs.synthetic.sam_masks import FaultRates

    path = Path(dataset) / "synthetic.json"
    if not path.is_file():
        raise InputError(path, "not found: the oracle needs a dataset written by thgs synth")
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        settings = dict(record["oracle"])
        settings["rates"] = FaultRates(**settings["rates"])
        settings["spurious_radius"] = tuple(settings["spurious_radius"])
        return OracleConfig(**settings), str(record["embedding_space"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise InputError(path, f"not a readable thgs synthetic record: {error!r}") from error


def _oracle_views(
    views: ViewsFolder,
    gaussians: Gaussians,
    source: OracleGuidance,
    raster: RasterConfig,
    progress: Progress | None,
) -> int:
    from thgs.eval.ground_truth import read_hierarchy
    from thgs.guidance import write_embedding_space, write_view_guidance
    from thgs.synthetic.oracle import oracle_guidance
    from thgs.text import load_text_encoder

    oracle, space = read_dataset_oracle(source.dataset)
    truth_path = source.dataset / "ground_truth.safetensors"
    hierarchy = read_hierarchy(truth_path)
    labelled = int(hierarchy.levels.labels.shape[0])
    if labelled != len(gaussians):
        raise InputError(
            truth_path,
            f"labels {labelled:,} Gaussians, the scene has "
            f"{len(gaussians):,}: not this scene's ground truth",
        )
    encoder = load_text_encoder(space)
    views.guidance.mkdir(parents=True, exist_ok=True)
    write_embedding_space(views.guidance, encoder.space, encoder.dim)

    def finished(stem: str) -> bool:
        return (views.guidance / f"{stem}_s.npy").is_file()

    def write(index: int, stem: str, max_id) -> None:
        guidance = oracle_guidance(stem, max_id, hierarchy, encoder, oracle, index)
        write_view_guidance(views.guidance, guidance)

    return render_views(
        views, gaussians, done=finished, on_view=write, raster=raster, progress=progress
    )


def _model_views(
    views: ViewsFolder,
    gaussians: Gaussians,
    source: ModelGuidance,
    raster: RasterConfig,
    progress: Progress | None,
) -> int:
    import torch

    from thgs.guidance.preprocess import (
        PreprocessConfig,
        image_jobs,
        load_preprocess_models,
        preprocess_images,
    )

    if source.dtype not in ("float32", "bfloat16", "float16"):
        raise InputError("--dtype", f"must be float32, bfloat16 or float16, got {source.dtype}")
    # the models first: a missing one stops the run before any rendering
    segmenter, encoder = load_preprocess_models(
        source.sam,
        source.clip,
        space=source.space,
        device=source.device,
        dtype=getattr(torch, source.dtype),
    )
    rendered = render_views(views, gaussians, raster=raster, progress=progress)
    jobs = image_jobs(views.images, cameras=views.cameras)
    done = 0

    def on_image(stem: str, seconds: float | None) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress("guidance", done, len(jobs))

    preprocess_images(
        jobs,
        views.guidance,
        segmenter,
        encoder,
        PreprocessConfig(masks=source.masks),
        on_image=on_image,
    )
    return rendered


def make_views_guidance(
    views: ViewsFolder,
    gaussians: Gaussians,
    source: GuidanceSource,
    *,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
) -> int:
    """Render the views of ``views`` and make their guidance in ``views.guidance``, skipping
    what a previous run finished.

    Returns:
        the number of views rendered now.

    Raises:
        InputError: a dataset that is not a thgs synthetic one or whose ground truth is not
            this scene's; models that cannot be found (each naming the file or model).
    """
    if isinstance(source, OracleGuidance):
        return _oracle_views(views, gaussians, source, raster, progress)
    return _model_views(views, gaussians, source, raster, progress)
