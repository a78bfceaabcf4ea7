"""Run a suite: for every scene, whatever of preprocess → build → eval is missing or stale
(:func:`thgs.suite.plan_scene` says which, :mod:`thgs.suite.plan` how it is decided).

Each stage is one library action: preprocessing :func:`thgs.guidance.preprocess.preprocess_images`,
the build :func:`thgs.workflows.build_field_file`, the evaluation
:func:`thgs.workflows.evaluate_field_file`; a finished stage is stamped after its outputs are
written.

A scene that fails (bad input, any exception) is reported with a one-line message and its
traceback in ``error.log``; the other scenes go on. In-process (the default) the scenes run one
after the other; with Ray each scene is a task with the CPUs and GPU its device needs, and the
suite's preprocessing a Ray Data pipeline over all its images. Both give the same report, timings
aside (:meth:`thgs.suite.SuiteReport.comparable`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from thgs._atomic import atomic_output
from thgs._json import load_json
from thgs.errors import InputError, ThgsError
from thgs.suite.config import SuiteConfig
from thgs.suite.discover import SuiteScene
from thgs.suite.plan import (
    EVAL,
    FIELD,
    GUIDANCE,
    STAGES,
    plan_scene,
    read_stamps,
    scene_folder,
    scene_guidance,
    stage_digest,
    write_stamp,
)
from thgs.suite.report import SceneResult, SuiteReport

__all__ = [
    "run_scene",
    "run_suite",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, str], None]
"""``progress(scene key, state)``: a scene's state as the suite advances (``"preprocess"``,
``"build"``, ``"eval"`` when a stage starts; ``"done"``, ``"current"`` or ``"failed: …"``)."""


ERROR_LOG = "error.log"


# --- the stages -----------------------------------------------------------------------------------


def _preprocess(scene: SuiteScene, folder: Path, config: SuiteConfig, models) -> dict[str, Any]:
    import torch

    from thgs.guidance.preprocess import image_jobs, load_preprocess_models, preprocess_images
    from thgs.scene import load_cameras

    assert scene.images is not None
    cameras = load_cameras(scene.data)[0]
    jobs = image_jobs(scene.images, cameras=cameras)
    if models is None:
        models = load_preprocess_models(
            config.sam, config.clip, device=_torch_device(config.device), dtype=torch.float32
        )
    segmenter, encoder = models
    summary = preprocess_images(jobs, folder / GUIDANCE, segmenter, encoder, config.preprocess)
    return {"images": len(jobs), "masks": list(summary.masks)}


def _torch_device(device: str) -> str:
    from thgs.device import resolve_device

    return str(resolve_device(device))


def _build(scene: SuiteScene, folder: Path, config: SuiteConfig) -> dict[str, Any]:
    from thgs.workflows import BuildRequest, build_field_file

    assert scene.model is not None
    request = BuildRequest(
        scene=scene.model,
        out=folder / FIELD,
        config=config.field_config(scene.benchmark),
        guidance=scene_guidance(scene, folder),
        source=None if scene.model == scene.data else scene.data,
        device=config.device,
    )
    built = build_field_file(request).field
    return {"timings": dict(built.timings), "regions": list(built.region_counts)}


def _evaluate(scene: SuiteScene, folder: Path, config: SuiteConfig) -> dict[str, Any]:
    from thgs.workflows import EvalRequest, evaluate_field_file

    request = EvalRequest(
        dataset=scene.data,
        field=folder / FIELD,
        out=folder / EVAL,
        protocols=scene.protocols,
        selection=config.selection,
        scannet_level=config.scannet_level,
        device=config.device,
    )
    evaluate_field_file(request, scene.ground_truth)
    return {}


def _metrics(folder: Path) -> dict[str, dict[str, float | None]]:
    document = load_json(folder / EVAL)
    if not isinstance(document, dict) or not isinstance(document.get("results"), list):
        raise InputError(folder / EVAL, "is not a thgs eval report (no 'results' list)")
    return {result["protocol"]: dict(result["metrics"]) for result in document["results"]}


def _one_line(error: BaseException) -> str:
    if isinstance(error, ThgsError):
        text = str(error)
    elif isinstance(error, OSError) and error.filename:
        text = f"{error.filename}: {error.strerror or error}"
    else:
        text = f"{type(error).__name__}: {error}"
    return " ".join(text.split())


def _recorded(scene: SuiteScene, folder: Path, stages: dict[str, str], error: str | None):
    stamps = read_stamps(folder)
    build = stamps.get("build", {})
    return SceneResult(
        scene.benchmark,
        scene.name,
        stages,
        metrics=_metrics(folder) if error is None else {},
        regions=tuple(build.get("regions", ())),
        build_seconds=dict(build.get("timings", {})),
        seconds={
            stage: stamps[stage]["seconds"]
            for stage in STAGES
            if isinstance(stamps.get(stage), dict) and "seconds" in stamps[stage]
        },
        error=error,
    )


def run_scene(
    scene: SuiteScene,
    out: str | os.PathLike[str],
    config: SuiteConfig,
    *,
    models: tuple[Any, Any] | None = None,
    progress: Progress | None = None,
) -> SceneResult:
    """Run what is missing or stale of one scene's stages (module docstring) and return what
    became of it. Never raises for a failing scene: the failure is in the result (and the
    traceback in ``OUT/<benchmark>/<scene>/error.log``); only an interruption
    (``KeyboardInterrupt``) propagates, leaving the scene resumable.

    Args:
        scene: from :func:`thgs.suite.find_suite`.
        out: the suite's output folder.
        config: the suite's settings.
        models: SAM and CLIP already loaded
            (:func:`thgs.guidance.preprocess.load_preprocess_models`), shared by the scenes of
            an in-process run; None: loaded here when needed.
        progress: called with the scene's key and the stage starting, then its end state.
    """
    folder = scene_folder(out, scene)
    stages = dict.fromkeys(STAGES, "not run")
    if scene.problems:
        return SceneResult(scene.benchmark, scene.name, stages, error="; ".join(scene.problems))

    def report(state: str) -> None:
        if progress is not None:
            progress(scene.key, state)

    stage = STAGES[0]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for plan in plan_scene(scene, out, config):
            stage = plan.stage
            if plan.action != "run":
                stages[stage] = plan.action
                continue
            report(stage)
            started = time.perf_counter()
            if stage == "preprocess":
                extra = _preprocess(scene, folder, config, models)
            elif stage == "build":
                extra = _build(scene, folder, config)
            else:
                extra = _evaluate(scene, folder, config)
            seconds = time.perf_counter() - started
            digest = stage_digest(scene, folder, config, stage)
            write_stamp(folder, stage, {"digest": digest, "seconds": seconds, **extra})
            stages[stage] = "ran"
        result = _recorded(scene, folder, stages, None)
    except Exception as error:  # any failure of one scene is reported; the others go on
        message = _one_line(error)
        stages[stage] = "failed"
        with atomic_output(folder / ERROR_LOG, "w") as handle:
            handle.write(traceback.format_exc())
        logger.error("%s failed: %s", scene.key, message)
        report(f"failed: {message}")
        return SceneResult(scene.benchmark, scene.name, stages, error=message)
    with contextlib.suppress(FileNotFoundError):
        (folder / ERROR_LOG).unlink()
    report("done" if "ran" in stages.values() else "current")
    return result


# --- the suite ------------------------------------------------------------------------------------


@contextlib.contextmanager
def _connect(address: str | None) -> Iterator[Any]:
    """Ray, connected (:func:`thgs.cluster.connect_ray`): to the cluster at ``address`` or, for
    None, a local Ray started here and shut down afterwards. A Ray already initialised in this
    process is used as it is.

    Raises:
        ThgsError: Ray is not installed, or the cluster does not answer.
    """
    from thgs.cluster import connect_ray

    with connect_ray(address):
        import ray

        yield ray


def _run_in_process(scenes, out, config, progress) -> list[SceneResult]:
    models = None
    results = []
    for scene in scenes:
        wants = not scene.problems and scene.guidance is None
        if wants and models is None and _plans_preprocessing(scene, out, config):
            import torch

            from thgs.guidance.preprocess import load_preprocess_models

            models = load_preprocess_models(
                config.sam, config.clip, device=_torch_device(config.device), dtype=torch.float32
            )
        results.append(run_scene(scene, out, config, models=models, progress=progress))
    return results


def _plans_preprocessing(scene: SuiteScene, out, config: SuiteConfig) -> bool:
    try:
        return plan_scene(scene, out, config)[0].action == "run"
    except (InputError, OSError):
        return False


def _end_state(result: SceneResult) -> str:
    if not result.ok:
        return f"failed: {result.error}"
    return "done" if "ran" in result.stages.values() else "current"


def _resources(ray, device: str) -> dict[str, float]:
    gpus = 1.0 if device == "cuda" else 0.0
    if device == "auto" and ray.cluster_resources().get("GPU", 0) > 0:
        gpus = 1.0
    return {"num_cpus": 1, "num_gpus": gpus}


def _preprocess_on_ray(scenes, out, config, ray, progress) -> dict[str, str | None]:
    """Preprocess every scene that needs it in one Ray Data pipeline and stamp the scenes it
    finished. Returns scene key → None for each scene preprocessed here, or the one-line
    reason its preprocessing failed (the pipeline goes on past a failing image: other scenes'
    views are finished and stamped)."""
    from thgs.guidance.preprocess import image_jobs
    from thgs.guidance.preprocess.distributed import PreprocessTarget, preprocess_with_ray
    from thgs.guidance.preprocess.run import is_finished
    from thgs.scene import load_cameras

    outcome: dict[str, str | None] = {}
    waiting, targets = [], []
    for scene in scenes:
        if scene.problems or not _plans_preprocessing(scene, out, config):
            continue
        assert scene.images is not None
        try:
            jobs = image_jobs(scene.images, cameras=load_cameras(scene.data)[0])
        except (ThgsError, OSError) as error:
            outcome[scene.key] = _one_line(error)
            continue
        waiting.append(scene)
        targets.append(PreprocessTarget(tuple(jobs), scene_folder(out, scene) / GUIDANCE))
        if progress is not None:
            progress(scene.key, "preprocess")
    if not waiting:
        return outcome
    gpus = _resources(ray, config.device)["num_gpus"]
    started = time.perf_counter()
    failure = None
    try:
        summaries = preprocess_with_ray(
            targets,
            sam=config.sam,
            clip=config.clip,
            config=config.preprocess,
            device="cuda" if gpus else "cpu",
            gpus_per_actor=gpus,
        )
    except ThgsError as error:  # the first failing image; the others' views are written
        failure, summaries = _one_line(error), [None] * len(targets)
    seconds = (time.perf_counter() - started) / len(waiting)
    for scene, target, summary in zip(waiting, targets, summaries):
        if summary is None and not all(is_finished(target.output, j.stem) for j in target.jobs):
            outcome[scene.key] = f"preprocessing on Ray: {failure}"
            continue
        folder = scene_folder(out, scene)
        digest = stage_digest(scene, folder, config, "preprocess")
        extra = {"images": len(target.jobs)}
        if summary is not None:
            extra["masks"] = list(summary.masks)
        write_stamp(folder, "preprocess", {"digest": digest, "seconds": seconds, **extra})
        outcome[scene.key] = None
    return outcome


def _run_on_ray(scenes, out, config, ray, progress) -> list[SceneResult]:
    preprocessed = _preprocess_on_ray(scenes, out, config, ray, progress)
    task = ray.remote(run_scene).options(**_resources(ray, config.device), max_retries=0)
    results: list[SceneResult | None] = [None] * len(scenes)
    pending = {}
    for index, scene in enumerate(scenes):
        failure = preprocessed.get(scene.key)
        if failure is not None:
            stages = {**dict.fromkeys(STAGES, "not run"), "preprocess": "failed"}
            results[index] = SceneResult(scene.benchmark, scene.name, stages, error=failure)
            if progress is not None:
                progress(scene.key, f"failed: {failure}")
            continue
        pending[task.remote(scene, Path(out).resolve(), config)] = index
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            index = pending.pop(ready[0])
            scene = scenes[index]
            try:
                result = ray.get(ready[0])
            except ray.exceptions.RayError as error:  # the worker died (out of memory, killed)
                message = _one_line(error).splitlines()[0][:500]
                stages = {**dict.fromkeys(STAGES, "not run"), "build": "failed"}
                result = SceneResult(scene.benchmark, scene.name, stages, error=message)
            if scene.key in preprocessed:  # preprocessed by the pipeline above
                result = replace(result, stages={**result.stages, "preprocess": "ran"})
            results[index] = result
            if progress is not None:
                progress(scene.key, _end_state(result))
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    return [result for result in results if result is not None]


def run_suite(
    scenes: Sequence[SuiteScene],
    out: str | os.PathLike[str],
    config: SuiteConfig = SuiteConfig(),
    *,
    use_ray: bool = False,
    ray_address: str | None = None,
    progress: Progress | None = None,
):
    """Run every scene's missing stages and gather the suite's report.

    Args:
        scenes: from :func:`thgs.suite.find_suite`; results keep their order.
        out: the output folder (module docstring).
        config: the suite's settings.
        use_ray: run scenes as Ray tasks (and preprocessing as a Ray Data pipeline); Ray must
            be installed (``thgs[cluster]``).
        ray_address: the Ray cluster to connect to (``ray start --head`` prints it); None with
            ``use_ray`` starts a local Ray for this run. A Ray already initialised in this
            process is used as it is.
        progress: ``progress(scene key, state)`` as scenes advance.

    Returns:
        a :class:`thgs.suite.SuiteReport` (not yet written: :func:`thgs.suite.write_suite_report`).

    Raises:
        ThgsError: Ray is wanted but missing, or its cluster does not answer.
        KeyboardInterrupt: passed on; every output is whole or absent, the suite resumable.
    """
    config.check()
    out = Path(out)
    started = time.perf_counter()
    if use_ray:
        with _connect(ray_address) as ray:
            out.mkdir(parents=True, exist_ok=True)
            results = _run_on_ray(list(scenes), out, config, ray, progress)
        executor = "ray"
    else:
        out.mkdir(parents=True, exist_ok=True)
        results = _run_in_process(list(scenes), out, config, progress)
        executor = "in-process"
    return SuiteReport(
        scenes=tuple(results),
        settings=config.to_json(),
        field_configs={
            benchmark: config.field_config(benchmark).to_json()
            for benchmark in sorted({scene.benchmark for scene in scenes})
        },
        executor=executor,
        seconds=time.perf_counter() - started,
    )
