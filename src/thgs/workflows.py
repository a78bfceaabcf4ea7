"""One library function per user action: build a field, evaluate it, export from it, answer a
vocabulary.

``thgs build``, ``thgs eval``, ``thgs export`` and ``thgs catalog``, ``thgs suite``'s stages and
the demo call these and only format what they return, so each action has one implementation and
its files are written the same way whoever asks:

- :func:`build_field_file` — scene + guidance + settings → a field file, with the scene and text
  model recorded in its provenance (:class:`BuildRequest` → :class:`BuiltField`); from the
  splat alone, the guidance is first made on virtual views (:mod:`thgs.splat_views`);
- :func:`evaluate_field_file` — a field against a benchmark's ground truth → the JSON report and
  its markdown table, written together (:class:`EvalRequest` → :class:`EvalOutcome`);
- :func:`export_field_file` — selections as PLYs, the scene coloured by region, labels, the
  scene graph (:class:`ExportRequest` → :class:`ExportOutcome`), the whole set or none of it;
- :func:`catalog_field_file` — a whole vocabulary answered in one pass: one label per Gaussian,
  one PLY per phrase found, the phrase table (:class:`CatalogRequest` → :class:`CatalogOutcome`,
  :mod:`thgs.catalog`);
- :func:`query_config` — the query options of the commands (mode, level, top, threshold,
  smallest region) checked together and turned into a :class:`thgs.query.QueryConfig`.

Querying and picking write through :func:`thgs.results.write_query_results` and
:func:`thgs.results.write_pick_results`; the suite's own stage planning is in
:mod:`thgs.suite.plan`.

Error messages name the command line's options (``--source``, ``--level`` …): these functions
are what the commands run, and a library caller reads the option as the argument of the same
name.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from thgs.choices import SelectionMode
from thgs.errors import InputError, settings_as_flags
from thgs.field import SemanticField
from thgs.field_config import FieldConfig
from thgs.query import QueryConfig, Selection

if TYPE_CHECKING:
    from thgs.catalog import Catalog
    from thgs.eval.dataset import EvalReport, GroundTruth
    from thgs.scene_graph import SceneGraph
    from thgs.splat_views import SplatViewsRequest

__all__ = [
    "BuildRequest",
    "BuiltField",
    "CatalogOutcome",
    "CatalogRequest",
    "EvalOutcome",
    "EvalRequest",
    "ExportOutcome",
    "ExportRequest",
    "build_field_file",
    "catalog_field_file",
    "eval_table_path",
    "evaluate_field_file",
    "export_field_file",
    "query_config",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``, as :func:`thgs.pipeline.build_field` calls it."""

# --- build ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BuildRequest:
    """What to build: a scene, the masks and features of its views, the settings, the output.

    Attributes:
        scene: a trained 3DGS/2DGS model folder, a gsplat result folder or a ``.ply`` file
            (:func:`thgs.scene.load_scene`).
        out: the field file to write (atomically; replaced if it exists).
        config: the build settings (:func:`thgs.pipeline.chosen_field_config`).
        guidance: the ``language_features`` folder; None: the one in the scene's source (or its
            model's recorded training data), else in the scene folder.
        source, iteration, images, scale: :func:`thgs.scene.load_scene`'s.
        resize: resample masks whose size differs from their camera's instead of stopping.
        space: the features' embedding space; None: the guidance folder's record
            (``embedding.json``), else LangSplat's CLIP for 512-D features.
        text_model: the features' model folder, recorded in the field; None: the one the
            guidance folder records (if it exists).
        device: where to compute (:func:`thgs.device.resolve_device`).
        lift_cache: a folder to keep the lift in and reuse it from.
        ray: lift and partition as Ray tasks on the Ray this process is connected to
            (:func:`thgs.cluster.connect_ray`).
        splat_views: build from the splat alone: place virtual cameras, render them and make
            their guidance first (:func:`thgs.splat_views.prepare_splat_views`), then build
            from that folder; ``source``, ``guidance``, ``images``, ``scale`` and ``resize``
            must then be left unset.
    """

    scene: Path
    out: Path
    config: FieldConfig
    guidance: Path | None = None
    source: Path | None = None
    iteration: int | None = None
    images: str | None = None
    scale: float = 1.0
    resize: bool = False
    space: str | None = None
    text_model: Path | None = None
    device: str = "auto"
    lift_cache: Path | None = None
    ray: bool = False
    splat_views: SplatViewsRequest | None = None


@dataclass(frozen=True)
class BuiltField:
    """A field :func:`build_field_file` built and wrote.

    Attributes:
        field: the field as written (with its provenance and the build's timings).
        path: the field file.
        space: the embedding space of its features.
    """

    field: SemanticField
    path: Path
    space: str


def _unfound_source(loaded) -> str:
    """'' or, when the model's cfg_args (gsplat: cfg.yml) names training data that is not here,
    '; <why>'."""
    named = loaded.model_source
    if named is None or named.named is None or named.folder is not None:
        return ""
    return f"; {named.describe()}"


def _build_space(request: BuildRequest, guidance: Path, views) -> str:
    from thgs.guidance import EMBEDDING_FILE, guidance_space, read_embedding_space

    recorded = read_embedding_space(guidance)
    space = request.space
    if space is not None and recorded is not None and recorded[0] != space:
        raise InputError(
            "--space",
            f"{space!r}, but {guidance / EMBEDDING_FILE} records {recorded[0]!r}; leave "
            "--space out, or correct the file if it is wrong",
        )
    if space is None or recorded is not None:
        space = guidance_space(guidance, views)  # checks the file against the features
    return space


def _text_model(request: BuildRequest, guidance: Path) -> Path | None:
    from thgs.guidance import EMBEDDING_FILE, read_embedding_model

    if request.text_model is not None:
        return request.text_model
    model = read_embedding_model(guidance)
    if model is not None and not model.is_dir():
        logger.warning(
            "%s names the model folder %s, which does not exist: the field will not remember "
            "its text model (--text-model DIR records one)",
            guidance / EMBEDDING_FILE,
            model,
        )
        return None
    return model


def _with_splat_views(request: BuildRequest, progress: Progress | None) -> BuildRequest:
    """``request`` reading its cameras and guidance from the splat's views folder, made or
    resumed now."""
    from thgs.splat_views import prepare_splat_views

    assert request.splat_views is not None
    given = {
        "--source": request.source is not None,
        "--guidance": request.guidance is not None,
        "--images": request.images is not None,
        "--scale": request.scale != 1.0,
        "--resize": request.resize,
    }
    clashing = [flag for flag, set_ in given.items() if set_]
    if clashing:
        raise InputError(
            "--from-splat",
            f"makes its own cameras, renders and guidance; leave out {', '.join(clashing)}",
        )
    prepared = prepare_splat_views(
        request.scene,
        request.splat_views,
        iteration=request.iteration,
        device=request.device,
        progress=progress,
    )
    views = prepared.views
    return replace(request, source=views.path, guidance=views.guidance, splat_views=None)


def build_field_file(request: BuildRequest, *, progress: Progress | None = None) -> BuiltField:
    """Load the scene and its guidance, build the semantic field and write it to
    ``request.out`` (:func:`thgs.field.save_field`, atomic), its provenance recording the scene
    and the text model. With ``request.splat_views``, the cameras, renders and guidance are
    made from the splat first, in that folder.

    Raises:
        InputError: no cameras, no guidance folder, masks or features that do not fit their
            views, a space that disagrees with the guidance's record, a text model that is not
            a folder, or a lift cache that is a file — each naming the file or option, before
            the build starts.
    """
    from thgs.device import resolve_device
    from thgs.field import save_field
    from thgs.field_scene import record_scene, record_text_model
    from thgs.guidance import check_masks, guidance_folder, load_guidance
    from thgs.pipeline import build_field
    from thgs.scene import load_scene

    cache = request.lift_cache
    if cache is not None and cache.exists() and not cache.is_dir():
        raise InputError("--lift-cache", f"{cache} is a file; name a folder to keep lifts in")
    if request.text_model is not None and not request.text_model.is_dir():
        raise InputError("--text-model", f"{request.text_model} is not a folder")
    if request.splat_views is not None:
        request = _with_splat_views(request, progress)
    loaded = load_scene(
        request.scene,
        source=request.source,
        iteration=request.iteration,
        images=request.images,
        scale=request.scale,
    )
    if loaded.cameras is None:
        raise InputError(
            request.scene,
            f"no cameras{_unfound_source(loaded)}; pass --source with COLMAP or transforms.json, "
            "or build from the splat alone with --from-splat",
        )
    guidance = request.guidance
    if guidance is None:
        guidance = guidance_folder(request.scene, loaded.source)
        if not guidance.is_dir():
            raise InputError(
                guidance,
                f"language features folder not found{_unfound_source(loaded)}; pass --source "
                "with the training data folder that holds language_features/, or --guidance, "
                "or make guidance on renders of the splat with --from-splat",
            )
    views = load_guidance(guidance, loaded.cameras, resize=request.resize, lazy=True)
    check_masks(views, guidance)
    space = _build_space(request, guidance, views)
    model = _text_model(request, guidance)
    field = build_field(
        loaded.to(resolve_device(request.device)),
        views,
        request.config,
        space=space,
        progress=progress,
        lift_cache=cache,
        ray=request.ray,
    )
    field = record_scene(
        field,
        request.scene,
        source=loaded.source,
        iteration=request.iteration,
        images=request.images,
        scale=request.scale,
        field_path=request.out,
    )
    field = record_text_model(field, model)
    save_field(request.out, field)
    return BuiltField(field, request.out, space)


# --- evaluate -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EvalRequest:
    """What to score: a field, the benchmark ground truth found for its dataset, the report.

    Attributes:
        dataset: the scene's dataset folder (recorded in the report).
        field: the field file.
        out: the JSON report; its markdown table goes to :func:`eval_table_path`.
        protocols: the protocols to run; None: every one whose ground truth is present.
        selection: the selection rule scored: ``"auto"`` (thgs's) or ``"paper"`` (the paper's
            top 3 of parts and objects).
        scannet_level: the field level whose features classify ScanNet points.
        scene: the scene the field was built on, if not where the field records.
        text_model: the text model's folder, instead of the one the field records.
        device: where to render.
        other_scene: score the dataset even though its cameras are not the field scene's.
        rescale_labels: stretch 2-D labels whose aspect ratio is not their camera's.
    """

    dataset: Path
    field: Path
    out: Path
    protocols: tuple[str, ...] | None = None
    selection: Literal["auto", "paper"] = "auto"
    scannet_level: int = 3
    scene: Path | None = None
    text_model: Path | None = None
    device: str = "auto"
    other_scene: bool = False
    rescale_labels: bool = False


@dataclass(frozen=True)
class EvalOutcome:
    """What :func:`evaluate_field_file` measured and wrote.

    Attributes:
        report: every protocol's metrics and items (:class:`thgs.eval.dataset.EvalReport`).
        json_path, table_path: the report and its markdown table.
    """

    report: EvalReport
    json_path: Path
    table_path: Path


def eval_table_path(report: Path) -> Path:
    """The markdown table written beside a JSON eval report (``X.json`` → ``X.md``)."""
    return report.with_suffix(".md")


def evaluate_field_file(
    request: EvalRequest, ground_truth: GroundTruth, *, progress: Progress | None = None
) -> EvalOutcome:
    """Score a field on ``ground_truth`` (:func:`thgs.eval.dataset.find_ground_truth`) and write
    the JSON report (every frame and prompt; its ``info`` names the dataset and the field) and
    its markdown table, both or neither.

    Raises:
        InputError: the field or its scene cannot be loaded, the dataset's cameras are not the
            field scene's (unless ``other_scene``), or a protocol's ground truth is missing.
    """
    from thgs._atomic import atomic_files, atomic_output
    from thgs.eval.dataset import check_ground_truth_scene, evaluate_dataset
    from thgs.export import write_json
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.pipeline import lifted_raster
    from thgs.query import FieldQuery
    from thgs.splat_views import VIEWS_RECORD

    semantic, loaded = open_field_scene(request.field, request.scene, device=request.device)
    if not request.other_scene:
        try:
            check_ground_truth_scene(request.dataset, loaded.cameras)
        except InputError as error:
            views = loaded.source
            if request.scene is None and views is not None and (views / VIEWS_RECORD).is_file():
                raise InputError(
                    request.dataset,
                    f"the field was built from virtual views of its splat ({views}), not from "
                    "the cameras of the benchmark's frames; pass --scene with the model folder "
                    "or dataset those cameras belong to",
                ) from error
            raise
    encoder = field_text_encoder(semantic, request.field, request.text_model)
    engine = FieldQuery(semantic, encoder, source=str(request.field))
    if request.selection == "paper":
        engine = engine.using(mode="paper", levels=None)
    report = evaluate_dataset(
        ground_truth,
        engine,
        loaded.gaussians,
        loaded.cameras,
        protocols=request.protocols,
        scannet_level=request.scannet_level,
        raster=lifted_raster(semantic, str(request.field)),
        progress=progress,
        rescale_labels=request.rescale_labels,
    )
    document = report.to_json()
    document["info"] = {
        **document["info"],
        "dataset": str(request.dataset),
        "field": str(request.field),
    }
    table = eval_table_path(request.out)
    with atomic_files([request.out, table]) as (json_path, table_path):
        write_json(json_path, document)
        with atomic_output(table_path, "w") as handle:
            handle.write(report.table() + "\n")
    return EvalOutcome(report, request.out, table)


# --- query options --------------------------------------------------------------------------------


def query_config(
    mode: SelectionMode | None = None,
    level: int | None = None,
    top: int = 1,
    threshold: float | None = None,
    min_gaussians: int | None = None,
) -> QueryConfig:
    """The selection the query commands' options ask for, checked together.

    ``mode`` None means ``auto``, or ``level`` when a level is named; naming a level for the
    auto or paper mode (which choose their levels) is refused. ``threshold`` is the threshold
    mode's relevancy cut (:attr:`QueryConfig.threshold`) or the auto mode's minimum relevancy
    (:attr:`QueryConfig.min_relevancy`); the paper and level modes refuse it.

    Raises:
        InputError: naming the option (``--level``, ``--top``, ``--threshold``,
            ``--min-gaussians``).
    """
    if level is not None and level not in (1, 2, 3):
        raise InputError("--level", f"must be 1 sub-parts, 2 parts or 3 objects, got {level}")
    if mode is None:
        mode = "auto" if level is None else "level"
    if mode in ("auto", "paper") and level is not None:
        searched = "levels 1–3" if mode == "auto" else "levels 2 and 3"
        raise InputError("--level", f"the {mode} mode searches {searched}; use --mode level")
    if threshold is not None and mode in ("paper", "level"):
        raise InputError("--threshold", f"the {mode} mode uses no threshold")
    with settings_as_flags("level", "top", "threshold", "min_gaussians", min_relevancy="threshold"):
        return QueryConfig(
            mode=mode,
            level=3 if level is None else level,
            top=top,
            threshold=threshold if mode == "threshold" else None,
            min_relevancy=threshold if mode == "auto" else None,
            min_gaussians=min_gaussians,
        ).check()


# --- export ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExportRequest:
    """What to export from a field.

    Attributes:
        field: the field file.
        out: the folder for the query PLYs, the region-coloured PLY and the labels (created if
            missing); None when only the graph is asked for.
        queries: texts whose selections to write, one ``<query>.ply`` each plus
            ``selections.json``.
        query: how those queries select (:func:`query_config`).
        color_level: write ``regions-<level name>.ply``, the whole scene coloured by region at
            this level (0 superpoints … 3 objects); None: not.
        labels: write ``labels.npy`` (int32 [N, 4], levels 0–3) and ``labels.json``.
        graph: write the scene graph to this JSON file (:mod:`thgs.scene_graph`); None: not.
        vocabulary: a phrase file (:func:`thgs.catalog.read_vocabulary`) to name the graph's
            regions with; None: the graph has no names.
        seed: of the region colours.
        scene: the scene the field was built on, if not where the field records.
        text_model: the text model's folder, instead of the one the field records.
    """

    field: Path
    out: Path | None = None
    queries: tuple[str, ...] = ()
    query: QueryConfig = QueryConfig()
    color_level: int | None = None
    labels: bool = False
    graph: Path | None = None
    vocabulary: Path | None = None
    seed: int = 0
    scene: Path | None = None
    text_model: Path | None = None


@dataclass(frozen=True)
class ExportOutcome:
    """What :func:`export_field_file` wrote.

    Attributes:
        field: the field exported from.
        selections: each query's selection, in the order asked.
        files: every file written, in order (the graph last).
        graph: the scene graph written, if asked for.
    """

    field: SemanticField
    selections: tuple[Selection, ...]
    files: tuple[Path, ...]
    graph: SceneGraph | None = None


def _check_export(request: ExportRequest) -> tuple[str, ...]:
    """The vocabulary's phrases (none without one), after checking what ``request`` asks."""
    from thgs.catalog import read_vocabulary

    to_folder = bool(request.queries) or request.color_level is not None or request.labels
    if not to_folder and request.graph is None:
        raise InputError(
            "thgs export", "nothing to export: pass --query, --color-level, --labels or --graph"
        )
    if to_folder and request.out is None:
        raise InputError(
            "--out", "--query, --color-level and --labels write into a folder: name it"
        )
    if request.color_level is not None and request.color_level not in (0, 1, 2, 3):
        raise InputError("--color-level", f"must be 0, 1, 2 or 3, got {request.color_level}")
    if request.graph is not None and request.graph.is_dir():
        raise InputError(request.graph, "is a folder; name the graph's JSON file, e.g. graph.json")
    if request.vocabulary is not None and request.graph is None:
        raise InputError("--vocabulary", "names the graph's regions: pass --graph too")
    return () if request.vocabulary is None else read_vocabulary(request.vocabulary)


def export_field_file(request: ExportRequest) -> ExportOutcome:
    """Write what ``request`` asks for: all of it, or (on any failure or interruption) none of
    it, and the output folder removed again if it was made here and is empty.

    Raises:
        InputError: nothing asked for, folder outputs without a folder, a level out of range, a
            graph path that is a folder, a bad vocabulary, the field or its scene cannot be
            loaded, or a file that cannot be written (named) — the checks before any loading.
    """
    from thgs.export import write_labels, write_region_ply
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.hierarchy.levels import LEVEL_NAMES
    from thgs.query import FieldQuery
    from thgs.results import write_query_selections
    from thgs.scene_graph import scene_graph, write_scene_graph

    phrases = _check_export(request)
    semantic, loaded = open_field_scene(request.field, request.scene)
    out = request.out
    created = out is not None and not out.exists()
    written: list[Path] = []
    selections: tuple[Selection, ...] = ()
    graph = None
    engine = None
    if request.queries or phrases:
        encoder = field_text_encoder(semantic, request.field, request.text_model)
        engine = FieldQuery(semantic, encoder, request.query, source=str(request.field))
    regions = [f"regions-{name}" for name in LEVEL_NAMES]  # never a query's name
    try:
        if request.queries:
            assert out is not None and engine is not None
            selections, paths = write_query_selections(
                out,
                engine,
                request.queries,
                loaded.gaussians,
                field_name=str(request.field),
                taken=regions,
            )
            written += paths
        if request.color_level is not None:
            assert out is not None
            path = out / f"{regions[request.color_level]}.ply"
            level = request.color_level
            write_region_ply(path, loaded.gaussians, semantic, level, seed=request.seed)
            written.append(path)
        if request.labels:
            assert out is not None
            for path in (out / "labels.npy", out / "labels.json"):
                write_labels(path, semantic)
                written.append(path)
        if request.graph is not None:
            graph = scene_graph(
                semantic,
                loaded.gaussians,
                engine=engine,
                vocabulary=phrases,
                field_name=str(request.field),
            )
            write_scene_graph(request.graph, graph)
            written.append(request.graph)
    except BaseException:
        for path in written:  # the whole set or none of it
            path.unlink(missing_ok=True)
        if created:
            assert out is not None
            with contextlib.suppress(OSError):  # only if nothing else was put there
                out.rmdir()
        raise
    return ExportOutcome(semantic, selections, tuple(written), graph)


# --- catalog --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CatalogRequest:
    """A vocabulary to answer on a field, and where the catalog goes.

    Attributes:
        field: the field file.
        vocabulary: the phrase file (:func:`thgs.catalog.read_vocabulary`: one phrase per line).
        out: the folder to write into (created if missing; files of the same names replaced).
        query: how each phrase selects (default: the automatic selection).
        scene: the scene the field was built on, if not where the field records.
        text_model: the text model's folder, instead of the one the field records.
        pictures: picture each phrase found in the view of the field's scene that shows most
            of it (``<phrase>.png``; a scene without cameras gets none). Rendering costs more
            than the rest of the catalog on a CPU.
    """

    field: Path
    vocabulary: Path
    out: Path
    query: QueryConfig = QueryConfig()
    scene: Path | None = None
    text_model: Path | None = None
    pictures: bool = False


@dataclass(frozen=True)
class CatalogOutcome:
    """What :func:`catalog_field_file` found and wrote.

    Attributes:
        catalog: every phrase's selection and the label of every Gaussian.
        files: every file written (``labels.npy``, ``labels.ply``, ``catalog.json``,
            ``catalog.md``, then one PLY per phrase found).
    """

    catalog: Catalog
    files: tuple[Path, ...]


def catalog_field_file(request: CatalogRequest) -> CatalogOutcome:
    """Read the vocabulary, answer every phrase on the field and write the catalog
    (:mod:`thgs.catalog`): the whole set, or none of it.

    Raises:
        InputError: a vocabulary file that is missing, not text, empty or repeats a phrase
            (named before the field is opened); a field or scene that cannot be loaded; a file
            that cannot be written.
    """
    from thgs.catalog import catalog_field, read_vocabulary, write_catalog
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.pipeline import lifted_raster
    from thgs.query import FieldQuery

    phrases = read_vocabulary(request.vocabulary)
    semantic, loaded = open_field_scene(request.field, request.scene)
    encoder = field_text_encoder(semantic, request.field, request.text_model)
    engine = FieldQuery(semantic, encoder, request.query, source=str(request.field))
    catalog = catalog_field(engine, phrases)
    cameras = loaded.cameras if request.pictures else None
    if request.pictures and cameras is None:
        logger.warning("%s: the field's scene has no cameras, so no pictures", request.field)
    files = write_catalog(
        request.out,
        catalog,
        loaded.gaussians,
        engine,
        field_name=str(request.field),
        cameras=cameras,
        raster=lifted_raster(semantic, str(request.field)),
    )
    return CatalogOutcome(catalog, files)
