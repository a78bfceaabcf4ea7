"""Preprocessing many scenes' images at once, as one Ray Data pipeline over a Ray cluster.

:func:`preprocess_with_ray` does what :func:`thgs.guidance.preprocess.preprocess_images` does for
each of several ``language_features`` folders (:class:`PreprocessTarget`), with the same files as
the result, byte for byte:

- the driver (the calling process) checks and writes each folder's ``preprocess.json`` and
  ``embedding.json`` exactly as :func:`preprocess_images` does, and leaves out finished views;
- one Ray Data dataset holds every unfinished image of every folder, one image per block, and a
  pool of actors preprocesses it (``map_batches`` with a callable class): each actor loads SAM and
  CLIP once (:func:`thgs.guidance.preprocess.load_preprocess_models`), then reads, preprocesses and
  writes one view at a time with the code :func:`preprocess_images` runs, its two files atomically
  (``_s.npy`` last, so a crashed or cancelled run resumes like an in-process one), with as many
  torch threads as Ray gives it CPUs (one);
- only a small row per image comes back through Ray's object store (its folder, stem, seconds,
  masks per level, and the error if it failed), never the masks or features.

Requirements on the cluster: every node sees the images, the models and the output folders at the
same paths (a shared filesystem; relative paths are made absolute in the driver's working
directory first), and has thgs installed with the ``models`` and ``cluster`` extras. Ray must be
initialised by the caller (:func:`thgs.cluster.connect_ray`).

An image that cannot be read does not stop the others: every view that can be made is written,
then the first error in the targets' order is raised as the worker raised it (an
:class:`thgs.errors.InputError` naming the file), and the others are logged.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from thgs.errors import InputError, ThgsError
from thgs.guidance.preprocess.clip_features import CLIPImageEncoder
from thgs.guidance.preprocess.models import load_preprocess_models, local_model_folder
from thgs.guidance.preprocess.run import (
    FolderRecord,
    ImageJob,
    PreprocessConfig,
    PreprocessSummary,
    ViewResult,
    is_finished,
    prepare_folder,
    preprocess_view,
    summarize,
)
from thgs.guidance.preprocess.sam import PointSegmenter

__all__ = ["PreprocessTarget", "preprocess_with_ray"]

logger = logging.getLogger(__name__)

DTYPES = ("float32", "bfloat16", "float16")
"""The models' precisions a distributed run accepts, by name."""

MAX_TASKS_PER_ACTOR = 2
"""Images queued on an actor at once: one running and one waiting, so an actor never idles
between images while the last images still spread over all actors."""


@dataclass(frozen=True)
class PreprocessTarget:
    """One scene's images and the ``language_features`` folder they go to.

    Attributes:
        jobs: the images, from :func:`thgs.guidance.preprocess.image_jobs`.
        output: the folder (created if missing).
    """

    jobs: tuple[ImageJob, ...]
    output: Path


@dataclass(frozen=True)
class _Models:
    """What each Ray worker loads: the ``--sam`` / ``--clip`` values, with local folders made
    absolute, and the device and precision."""

    sam: str
    clip: str
    space: str | None
    device: str
    dtype: str

    def load(self) -> tuple[PointSegmenter, CLIPImageEncoder]:
        return load_preprocess_models(
            self.sam,
            self.clip,
            space=self.space,
            device=self.device,
            dtype=getattr(torch, self.dtype),
        )


def _absolute_if_folder(value: str) -> str:
    folder = local_model_folder(value)
    return value if folder is None else os.path.abspath(folder)


def _folder_record(models: _Models, config: PreprocessConfig) -> FolderRecord | bytes:
    """The record the models make in a folder, loaded where the actors will run; a
    :class:`ThgsError` (missing weights, a wrong model) comes back pickled."""
    try:
        return FolderRecord.of(*models.load(), config)
    except ThgsError as error:
        return pickle.dumps(error)


class _ViewWorker:
    """A Ray Data actor: loads the models once, then preprocesses batches of rows (``target``,
    ``path``, ``stem``, ``width``, ``height``, ``output``; width and height −1 for LangSplat's
    size) into their folders and returns one small row per image."""

    def __init__(self, models: _Models, config: PreprocessConfig):
        import ray

        # as many torch threads as CPUs Ray gave the actor, whatever the node's environment:
        # on a CPU, float sums in CLIP and SAM depend on the thread count in their last bit
        cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0)
        torch.set_num_threads(max(1, int(cpus)))
        self._segmenter, self._encoder = models.load()
        self._config = config

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        seconds, masks, errors = [], [], []
        for path, stem, width, height, output in zip(
            batch["path"], batch["stem"], batch["width"], batch["height"], batch["output"]
        ):
            size = None if width < 0 else (int(width), int(height))
            try:
                result = preprocess_view(
                    ImageJob(Path(path), str(stem), size),
                    Path(output),
                    self._segmenter,
                    self._encoder,
                    self._config,
                )
            except ThgsError as error:
                result, failure = ViewResult(str(stem), 0.0, (0, 0, 0, 0)), pickle.dumps(error)
            else:
                failure = b""
            seconds.append(result.seconds)
            masks.append(result.masks)
            errors.append(failure)
        return {
            "target": np.asarray(batch["target"], dtype=np.int64),
            "stem": np.asarray(batch["stem"], dtype=object),
            "seconds": np.asarray(seconds, dtype=np.float64),
            "masks": np.asarray(masks, dtype=np.int64).reshape(-1, 4),
            "error": np.asarray(errors, dtype=object),
        }


def _import_ray():
    try:
        import ray
        import ray.data
    except ImportError as error:
        raise ThgsError(
            "preprocessing on a Ray cluster needs Ray: pip install 'thgs[cluster]'"
        ) from error
    return ray


def _check_targets(targets: Sequence[PreprocessTarget]) -> list[PreprocessTarget]:
    """The targets with absolute paths; refuses two targets writing one folder and two images of
    one target sharing a stem."""
    absolute, seen = [], {}
    for index, target in enumerate(targets):
        output = Path(os.path.abspath(target.output))
        if output in seen:
            raise InputError(
                output, f"is the output of targets {seen[output]} and {index}; give each its own"
            )
        seen[output] = index
        stems = [job.stem for job in target.jobs]
        duplicates = sorted({stem for stem in stems if stems.count(stem) > 1})
        if duplicates:
            raise InputError(output, f"several images would write the views {duplicates[:5]}")
        jobs = tuple(
            ImageJob(Path(os.path.abspath(job.path)), job.stem, job.size) for job in target.jobs
        )
        absolute.append(PreprocessTarget(jobs, output))
    return absolute


def _actor_count(ray, actors: int | None, gpus_per_actor: float, images: int) -> int:
    if actors is not None:
        return actors
    resources = ray.cluster_resources()
    if gpus_per_actor > 0:
        capacity = int(resources.get("GPU", 0.0) // gpus_per_actor)
        if capacity == 0:
            raise ThgsError(
                f"the Ray cluster has {resources.get('GPU', 0.0):g} GPUs, and each actor needs "
                f"{gpus_per_actor:g}; start Ray with GPUs or set gpus_per_actor to 0 on a CPU"
            )
    else:
        capacity = int(resources.get("CPU", 1.0))
    return max(1, min(capacity, images))


def _run_pipeline(
    ray, rows: list[dict], models: _Models, config: PreprocessConfig, actors: int, gpus: float
) -> Iterator[tuple[tuple[int, str], ViewResult | ThgsError]]:
    """Run the rows through a pool of ``actors`` actors; yields each image's (target, stem) and
    its result or error, as the images finish."""
    dataset = ray.data.from_items(rows, override_num_blocks=len(rows))
    dataset.context.enable_progress_bars = False
    dataset.context.print_on_execution_start = False
    views = dataset.map_batches(
        _ViewWorker,
        fn_constructor_kwargs={"models": models, "config": config},
        compute=ray.data.ActorPoolStrategy(
            size=actors, max_tasks_in_flight_per_actor=MAX_TASKS_PER_ACTOR
        ),
        num_gpus=gpus,
        batch_size=1,
        batch_format="numpy",
    )
    for batch in views.iter_batches(batch_size=None, batch_format="numpy"):
        for target, stem, seconds, masks, error in zip(
            batch["target"], batch["stem"], batch["seconds"], batch["masks"], batch["error"]
        ):
            key = (int(target), str(stem))
            if error:
                yield key, pickle.loads(error)
            else:
                yield key, ViewResult(key[1], float(seconds), tuple(int(m) for m in masks))


def preprocess_with_ray(
    targets: Sequence[PreprocessTarget],
    *,
    sam: str,
    clip: str,
    space: str | None = None,
    config: PreprocessConfig = PreprocessConfig(),
    device: str = "cpu",
    dtype: str = "float32",
    actors: int | None = None,
    gpus_per_actor: float = 0.0,
    overwrite: bool = False,
    on_image: Callable[[str, float | None], None] | None = None,
) -> list[PreprocessSummary]:
    """Preprocess several folders' images on the Ray cluster this process is connected to.

    The files written are those :func:`thgs.guidance.preprocess.preprocess_images` writes with
    ``load_preprocess_models(sam, clip, space=space, device=device, dtype=dtype)``, byte for byte,
    except that a local model folder is recorded in ``preprocess.json`` by its absolute path. On
    a CPU that holds for an in-process run with one torch thread (``torch.set_num_threads(1)``),
    as each actor runs: other thread counts sum floats in another order, which changes features
    in their last bit.

    Args:
        targets: the folders and their images.
        sam, clip, space: the models, as :func:`thgs.guidance.preprocess.load_preprocess_models`
            reads them (a local folder or a Hugging Face id found in each node's cache).
        config: settings, as for :func:`preprocess_images`.
        device: the torch device each actor runs its models on (``cuda`` needs
            ``gpus_per_actor`` > 0, so that Ray gives each actor its GPU).
        dtype: the models' precision: float32, bfloat16 or float16.
        actors: the actors preprocessing at once, each holding its own SAM and CLIP; default as
            many as the cluster has room for (GPUs / ``gpus_per_actor``, or its CPUs), at most one
            per image to do.
        gpus_per_actor: GPUs Ray reserves for each actor (a fraction shares one GPU).
        overwrite: redo every view and replace each folder's record of models and settings.
        on_image: called in the driver after each image with its stem and seconds (None for a
            finished view skipped); skipped views first, then images as they finish, in any order.

    Returns:
        One summary per target, in the targets' order; ``done`` and ``empty`` in the order of
        each target's jobs.

    Raises:
        ThgsError: Ray is not installed or not initialised, or a model cannot be loaded.
        InputError: a folder was made with other models or settings (unless ``overwrite``), two
            targets share a folder, or an image is unreadable (raised after the other images are
            done).
    """
    ray = _import_ray()
    if not ray.is_initialized():
        raise ThgsError(
            "Ray is not initialised in this process: connect first with "
            "thgs.cluster.connect_ray() (or ray.init())"
        )
    if dtype not in DTYPES:
        raise InputError("dtype", f"must be one of {', '.join(DTYPES)}, not {dtype!r}")
    if device != "cpu" and gpus_per_actor <= 0:
        raise InputError(
            "gpus_per_actor", f"is {gpus_per_actor:g}; device {device!r} needs a GPU per actor"
        )
    if actors is not None and actors < 1:
        raise InputError("actors", f"must be at least 1, not {actors}")
    if not targets:
        return []
    targets = _check_targets(targets)
    models = _Models(_absolute_if_folder(sam), _absolute_if_folder(clip), space, device, dtype)

    start = time.perf_counter()
    record = ray.get(
        ray.remote(_folder_record)
        .options(num_gpus=gpus_per_actor, max_retries=0)
        .remote(models, config)
    )
    if isinstance(record, bytes):
        raise pickle.loads(record)
    logger.info("models loaded on a Ray worker in %.1f s", time.perf_counter() - start)
    rows, skipped = [], []
    for index, target in enumerate(targets):
        prepare_folder(target.output, record, overwrite)
        skipped.append([])
        for job in target.jobs:
            if not overwrite and is_finished(target.output, job.stem):
                skipped[-1].append(job.stem)
                if on_image is not None:
                    on_image(job.stem, None)
                continue
            width, height = job.size if job.size is not None else (-1, -1)
            rows.append(
                {
                    "target": index,
                    "path": str(job.path),
                    "stem": job.stem,
                    "width": width,
                    "height": height,
                    "output": str(target.output),
                }
            )

    results: dict[tuple[int, str], ViewResult] = {}
    failures: dict[tuple[int, str], ThgsError] = {}
    if rows:
        count = _actor_count(ray, actors, gpus_per_actor, len(rows))
        logger.info(
            "preprocessing %d images of %d folders on %d Ray actors (%g GPUs each, %s)",
            len(rows),
            len(targets),
            count,
            gpus_per_actor,
            device,
        )
        for key, result in _run_pipeline(ray, rows, models, config, count, gpus_per_actor):
            if isinstance(result, ThgsError):
                failures[key] = result
                continue
            results[key] = result
            if on_image is not None:
                on_image(result.stem, result.seconds)

    if failures:
        ordered = [
            failures[(row["target"], row["stem"])]
            for row in rows
            if (row["target"], row["stem"]) in failures
        ]
        for error in ordered[1:]:
            logger.error("%s", error)
        raise ordered[0]
    return [
        summarize(
            target.output,
            [results[(index, job.stem)] for job in target.jobs if (index, job.stem) in results],
            skipped[index],
            config,
        )
        for index, target in enumerate(targets)
    ]
