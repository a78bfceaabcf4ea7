"""``thgs query``, ``thgs pick`` and ``thgs export``: use a semantic field."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import tyro
from rich.table import Table

from thgs.choices import Device, SelectionMode
from thgs.cli._console import setup_logging, stdout
from thgs.cli._outputs import check_output_file, check_output_folder
from thgs.errors import InputError, ThgsError

__all__ = ["catalog", "export", "pick", "query"]


def _field_query(field_path: Path, field, text_model: Path | None, config):
    from thgs.field_scene import field_text_encoder
    from thgs.query import FieldQuery

    encoder = field_text_encoder(field, field_path, text_model)
    return FieldQuery(field, encoder, config, source=str(field_path))


def _selection_table(title: str, field, selections) -> Table:
    from thgs.hierarchy.levels import LEVEL_NAMES

    table = Table(title=title, title_justify="left")
    columns = ("query", "confidence", "regions (level region: relevancy, Gaussians)", "Gaussians")
    for column in columns:
        table.add_column(column)
    for selection in selections:
        regions = "; ".join(
            f"{LEVEL_NAMES[k]} {r}: {score:.3f}, {int(field.sizes(k)[r]):,}"
            for k, r, score in selection.regions
        )
        confidence = selection.confidence
        table.add_row(
            selection.text,
            "" if confidence is None else f"{confidence:.2f}",
            regions or selection.reason or "nothing relevant",
            f"{int(selection.gaussians.sum()):,}",
        )
    return table


def query(
    field: Path,
    texts: tuple[str, ...],
    /,
    *,
    mode: SelectionMode | None = None,
    level: int | None = None,
    top: int = 1,
    threshold: float | None = None,
    min_gaussians: int | None = None,
    views: tuple[str, ...] = (),
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
    relevancy: bool = False,
    mask_threshold: float = 0.5,
    scene: Path | None = None,
    text_model: Path | None = None,
    device: Device = "auto",
    verbose: bool = False,
) -> None:
    """Ask a semantic field in words: which regions, how many Gaussians, and where in the views.

    Prints each query's regions. With --out it writes results.json, and with --views the 2D
    masks (the selection's rendered opacity above --mask-threshold) as <out>/<query>/<view>.png.

    Args:
        field: the field file (thgs build).
        texts: one or more queries, e.g. mug "teddy bear".
        mode: auto (per query: the regions named like it, at the level where they are so
            named, or nothing when nothing is relevant), paper (the paper's: top 3 of levels 2
            and 3, no threshold), level (the --top best regions of --level) or threshold (every
            region of --level above --threshold, possibly none). Default: auto, or level when
            --level is given.
        level: 1 sub-parts, 2 parts, 3 objects (level and threshold modes; default 3).
        top: level mode: how many regions.
        threshold: threshold mode: relevancy needed (default: the embedding space's, 0.8 for
            MiniLM, 0.5 for CLIP); auto mode: the relevancy the best region needs (default: none;
            auto abstains when the best region is no closer than ordinary names get in this
            scene, docs/query.md).
        min_gaussians: never select regions with fewer Gaussians (default: the field's
            small-region size, 20 for the LERF preset; 0 to allow every region).
        views: view names (image stems) to draw masks in, "all", or "best": each query in
            the one view that shows most of its selection (every view is rendered to find it).
        out: folder for results.json and the masks.
        relevancy: also write per-pixel relevancy maps (<view>-relevancy-<level>.png, 0–255).
        mask_threshold: rendered opacity above which a pixel is in the mask.
        scene: the scene the field was built on, if not where the field says.
        text_model: the text model's local folder, instead of the one the field records (or,
            for a field that records none, the Hugging Face cache).
        device: where to render: auto (a CUDA GPU if torch sees one, else MPS, else the CPU),
            cpu, cuda or mps (docs/rendering.md).
        verbose: log what is loaded and how long it takes.
    """
    from thgs.field import load_field
    from thgs.field_scene import find_view, open_field_scene
    from thgs.pipeline import lifted_raster
    from thgs.results import write_query_results
    from thgs.workflows import query_config

    setup_logging(verbose)
    if out is not None:
        check_output_folder(out)
    if not texts:
        raise InputError("thgs query", "give at least one query text")
    if (views or relevancy) and out is None:
        raise InputError("--views", "masks and relevancy maps are written to files: pass --out")
    if relevancy and not views:
        raise InputError("--relevancy", "name the views to draw in with --views")
    config = query_config(mode, level, top, threshold, min_gaussians)
    if views:
        semantic, loaded = open_field_scene(field, scene, device=device)
    else:
        semantic, loaded = load_field(field), None
    fq = _field_query(field, semantic, text_model, config)
    if out is None:
        selections = fq.select(list(texts))
        stdout.print(_selection_table(f"thgs query {field} ({config.mode})", semantic, selections))
        return
    cameras = None
    best = views == ("best",)
    if loaded is not None:
        wanted = loaded.cameras.stems if views in (("all",), ("best",)) else views
        where = loaded.cameras_path or loaded.ply_path
        cameras = loaded.cameras.select([find_view(loaded.cameras, name, where) for name in wanted])
    written = write_query_results(
        out,
        fq,
        texts,
        field_name=str(field),
        gaussians=None if loaded is None else loaded.gaussians,
        cameras=cameras,
        mask_threshold=mask_threshold,
        relevancy=relevancy,
        best_view=best,
        raster=lifted_raster(semantic, str(field)),
    )
    stdout.print(
        _selection_table(f"thgs query {field} ({config.mode})", semantic, written.selections)
    )
    count = 0 if cameras is None else len(cameras)
    masks = f" and masks for {count} view{'s' if count != 1 else ''}" if count else ""
    if best:
        masks = " and each query's mask in the view that shows most of it"
    stdout.print(f"wrote {written.results}{masks}")


def pick(
    field: Path,
    /,
    *,
    view: str,
    pixel: tuple[int, int],
    level: int = 1,
    scene: Path | None = None,
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
    device: Device = "auto",
    verbose: bool = False,
) -> None:
    """Click a pixel: the Gaussian under it and its region at every level.

    Prints the region chain from superpoint to object and the picked level's parent and
    children. With --out it writes pick.json, the region's mask in that view and its Gaussians
    as a PLY.

    Args:
        field: the field file (thgs build).
        view: the view's name (image stem).
        pixel: X Y, column and row from the top-left corner.
        level: the level to select: 0 superpoints, 1 sub-parts, 2 parts, 3 objects.
        scene: the scene the field was built on, if not where the field says.
        out: folder for pick.json, the mask PNG and the region's PLY.
        device: where to render: auto (a CUDA GPU if torch sees one, else MPS, else the CPU),
            cpu, cuda or mps (docs/rendering.md).
        verbose: log what is loaded.
    """
    from thgs.field_scene import find_view, open_field_scene
    from thgs.hierarchy.levels import LEVEL_NAMES
    from thgs.pipeline import lifted_raster
    from thgs.results import pick_summary, write_pick_results
    from thgs.views import pick as pick_pixel

    setup_logging(verbose)
    if out is not None:
        check_output_folder(out)
    if level not in (0, 1, 2, 3):
        raise InputError("--level", f"must be 0, 1, 2 or 3, got {level}")
    semantic, loaded = open_field_scene(field, scene, device=device)
    index = find_view(loaded.cameras, view, loaded.cameras_path or loaded.ply_path)
    camera = loaded.cameras.select([index])
    raster = lifted_raster(semantic, str(field))
    picked = pick_pixel(semantic, loaded.gaussians, camera, pixel, config=raster)
    if picked is None:
        raise ThgsError(f"{view}: no Gaussian at pixel ({pixel[0]}, {pixel[1]})")
    summary = pick_summary(semantic, picked, level)
    table = Table(
        title=f"thgs pick {view} ({pixel[0]}, {pixel[1]}): Gaussian {picked.gaussian}",
        title_justify="left",
    )
    for column in ("level", "region", "Gaussians", ""):
        table.add_column(column)
    for k, name in enumerate(LEVEL_NAMES):
        mark = "← picked" if k == level else ""
        size = int(semantic.sizes(k)[picked.regions[k]])
        table.add_row(f"{k} {name}", str(picked.regions[k]), f"{size:,}", mark)
    stdout.print(table)
    if level > 0:
        stdout.print(f"children at level {level - 1}: {summary['children']}")
    if out is None:
        return
    written = write_pick_results(
        out, semantic, loaded.gaussians, camera, picked, level, field_name=str(field), raster=raster
    )
    stdout.print(f"wrote {written.json}, {written.mask.name} and {written.ply.name}")


def export(
    field: Path,
    /,
    *,
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
    query: tuple[str, ...] = (),
    mode: SelectionMode | None = None,
    level: int | None = None,
    top: int = 1,
    threshold: float | None = None,
    min_gaussians: int | None = None,
    color_level: int | None = None,
    labels: bool = False,
    graph: Path | None = None,
    vocabulary: Path | None = None,
    seed: int = 0,
    scene: Path | None = None,
    text_model: Path | None = None,
    verbose: bool = False,
) -> None:
    """Take results elsewhere: selections as PLYs, the scene coloured by region, labels, the
    scene graph.

    Args:
        field: the field file (thgs build).
        out: folder to write the PLYs and labels into (not needed for --graph alone).
        query: texts whose selections to write, one <query>.ply each (the input's PLY layout)
            plus selections.json; the selection settings are thgs query's.
        mode: see thgs query.
        level: see thgs query.
        top: see thgs query.
        threshold: see thgs query.
        min_gaussians: see thgs query.
        color_level: write regions-<level>.ply, the whole scene coloured by region at this level
            (0 superpoints … 3 objects).
        labels: write labels.npy (int32 [N, 4], levels 0–3) and labels.json.
        graph: write the scene graph to this JSON file: every region of every level with its
            parent, children, size, centroid and boxes, its best names from --vocabulary, and
            which regions of a level touch (schema: docs/query.md).
        vocabulary: a text file of phrases (one per line) to name the graph's regions with.
        seed: of the region colours.
        scene: the scene the field was built on, if not where the field says.
        text_model: the text model's local folder, instead of the one the field records (or,
            for a field that records none, the Hugging Face cache).
        verbose: log what is loaded.
    """
    from thgs.query import QueryConfig
    from thgs.workflows import ExportRequest, export_field_file, query_config

    setup_logging(verbose)
    if out is not None:
        check_output_folder(out)
    if graph is not None:
        check_output_file(graph, "--graph")
    request = ExportRequest(
        field=field,
        out=out,
        queries=query,
        query=query_config(mode, level, top, threshold, min_gaussians) if query else QueryConfig(),
        color_level=color_level,
        labels=labels,
        graph=graph,
        vocabulary=vocabulary,
        seed=seed,
        scene=scene,
        text_model=text_model,
    )
    outcome = export_field_file(request)
    if query:
        title = f"thgs export {field} ({request.query.mode})"
        stdout.print(_selection_table(title, outcome.field, outcome.selections))
    if outcome.graph is not None:
        levels = [sum(node.level == k for node in outcome.graph.nodes) for k in range(4)]
        stdout.print(
            f"scene graph: {' / '.join(map(str, levels))} regions at levels 0–3, "
            f"{len(outcome.graph.edges)} touching pairs"
        )
    files = [p for p in outcome.files if p != graph]
    if files:
        stdout.print(f"wrote {len(files)} files to {out}/: " + ", ".join(p.name for p in files))
    if graph is not None:
        stdout.print(f"wrote {graph}")


def catalog(
    field: Annotated[Path, tyro.conf.arg(metavar="FIELD")],
    vocabulary: Annotated[Path, tyro.conf.arg(metavar="VOCABULARY")],
    /,
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
    mode: SelectionMode | None = None,
    level: int | None = None,
    top: int = 1,
    threshold: float | None = None,
    min_gaussians: int | None = None,
    scene: Path | None = None,
    text_model: Path | None = None,
    pictures: bool = False,
    verbose: bool = False,
) -> None:
    """Answer a whole vocabulary in one pass: one label per Gaussian, one PLY per phrase found.

    Every phrase is selected as thgs query would (the automatic selection by default); each
    Gaussian gets the phrase that claims it most confidently (ties: the smaller region, then
    the phrase listed first), -1 if none. Writes labels.npy (int32 [N], in the scene PLY's
    order), labels.ply (the scene with a label property), <phrase>.ply for each phrase found,
    with --pictures <phrase>.png (the view that shows most of it, the selection tinted),
    catalog.json and catalog.md (what was found, confidences, why the others were not).

    Args:
        field: the field file (thgs build).
        vocabulary: a text file with one phrase per line (blank lines and # comments skipped).
        out: folder to write into.
        mode: see thgs query.
        level: see thgs query.
        top: see thgs query.
        threshold: see thgs query.
        min_gaussians: see thgs query.
        scene: the scene the field was built on, if not where the field says.
        text_model: the text model's local folder, instead of the one the field records (or,
            for a field that records none, the Hugging Face cache).
        pictures: also picture each phrase found in the best of 12 views of the field's scene
            (<phrase>.png: the view beside the same with the selection tinted); rendering costs
            more than the rest of the catalog on a CPU.
        verbose: log what is loaded.
    """
    from thgs.workflows import CatalogRequest, catalog_field_file, query_config

    setup_logging(verbose)
    check_output_folder(out)
    request = CatalogRequest(
        field=field,
        vocabulary=vocabulary,
        out=out,
        query=query_config(mode, level, top, threshold, min_gaussians),
        scene=scene,
        text_model=text_model,
        pictures=pictures,
    )
    outcome = catalog_field_file(request)
    result = outcome.catalog
    table = Table(
        title=f"thgs catalog {field} ({result.mode}): {len(result.entries)} phrases",
        title_justify="left",
    )
    for column in ("label", "phrase", "confidence", "Gaussians (kept)", "found"):
        table.add_column(column)
    for entry in result.entries:
        confidence = entry.selection.confidence
        table.add_row(
            str(entry.index),
            entry.phrase,
            "" if confidence is None else f"{confidence:.2f}",
            f"{int(entry.selection.gaussians.sum()):,} ({entry.kept:,})",
            "yes" if entry.found else "no",
        )
    stdout.print(table)
    found = sum(entry.found for entry in result.entries)
    unlabelled = int((result.labels < 0).sum())
    stdout.print(
        f"{found} of {len(result.entries)} phrases found; {unlabelled:,} of "
        f"{len(result.labels):,} Gaussians carry none; wrote {len(outcome.files)} files to {out}/"
    )
