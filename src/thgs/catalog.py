"""A whole vocabulary answered in one pass: one label per Gaussian, one PLY per phrase found.

:func:`read_vocabulary` reads a phrase list (one phrase per line; blank lines and ``#`` comments
skipped; a phrase listed twice is an error naming both lines). :func:`catalog_field` answers every
phrase with the field's query engine (the automatic selection unless told otherwise) and gives
each Gaussian the phrase that claims it most confidently:

- a phrase *claims* the members of each region its selection chose, with that region's
  calibrated confidence (:attr:`thgs.query.Selection.region_confidence`; where the engine
  computes none, the region's relevancy stands in for every phrase alike);
- a Gaussian claimed by several phrases goes to the highest confidence; on a tie to the smaller
  region (the more specific answer: a handle rather than the mug around it), then to the phrase
  listed first;
- a Gaussian no phrase claims is labelled −1.

:func:`write_catalog` writes the result into a folder, the whole set or none of it::

    labels.npy        int32 [N]: the phrase index of every Gaussian, −1 for none, in the
                      scene PLY's order
    labels.ply        the scene's PLY with an int32 ``label`` property holding the same
    <phrase>.ply      every Gaussian the phrase's selection holds (before overlaps are
                      resolved), for each phrase found; names as ``thgs export`` gives them
    <phrase>.png      with cameras: the view (of :data:`PICTURE_VIEWS` spread over them)
                      that shows most of the phrase's selection
                      (:func:`thgs.views.best_views`), beside the same with the selection
                      tinted, for each phrase found and seen in one of them
    catalog.json      the phrase table: index, phrase, what was selected, confidences,
                      Gaussians selected and kept, the PLY, or why nothing was found
    catalog.md        the same as a table
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from thgs._atomic import atomic_files
from thgs.errors import InputError
from thgs.export import write_json, write_map_png, write_selection_ply
from thgs.query import FieldQuery, QueryConfig, Selection
from thgs.render import RasterConfig
from thgs.results import unique_names
from thgs.scene import Cameras, Gaussians, write_ply

__all__ = [
    "CATALOG_FILES",
    "PICTURE_CHOICE_SCALE",
    "PICTURE_VIEWS",
    "Catalog",
    "CatalogEntry",
    "catalog_field",
    "read_vocabulary",
    "write_catalog",
]

logger = logging.getLogger(__name__)

CATALOG_FILES = ("labels.npy", "labels.ply", "catalog.json", "catalog.md")
"""The files every catalog folder holds, beside one PLY per phrase found."""

_MAX_VOCABULARY_BYTES = 10_000_000


def read_vocabulary(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """The phrases of a vocabulary file: one per line, white space around them dropped, blank
    lines and lines starting with ``#`` skipped, in file order.

    Raises:
        InputError: naming the file: missing, a folder, not UTF-8 text (or holding NUL bytes),
            larger than 10 MB, without any phrase, or listing a phrase twice (both lines named;
            phrases are compared as written, case and inner spaces included).
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder; give a text file with one phrase per line")
    if not path.is_file():
        raise InputError(path, "vocabulary file not found")
    if path.stat().st_size > _MAX_VOCABULARY_BYTES:
        raise InputError(
            path, f"is larger than {_MAX_VOCABULARY_BYTES // 1_000_000} MB; is it a vocabulary?"
        )
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise InputError(
            path, f"is not UTF-8 text (byte {error.start}); give one phrase per line"
        ) from error
    if "\x00" in text:
        raise InputError(path, "holds NUL bytes: not a text file")
    seen: dict[str, int] = {}
    phrases: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        phrase = line.strip()
        if not phrase or phrase.startswith("#"):
            continue
        if phrase in seen:
            raise InputError(
                path, f"line {number} repeats {phrase!r} of line {seen[phrase]}; list it once"
            )
        seen[phrase] = number
        phrases.append(phrase)
    if not phrases:
        raise InputError(path, "holds no phrase (blank lines and # comments only)")
    return tuple(phrases)


@dataclass(frozen=True)
class CatalogEntry:
    """One phrase of a catalog.

    Attributes:
        index: the phrase's label value (its position in the vocabulary).
        phrase: the phrase.
        selection: what the query engine selected for it (:class:`thgs.query.Selection`).
        kept: how many of the selected Gaussians carry its label once overlaps are resolved.
    """

    index: int
    phrase: str
    selection: Selection
    kept: int

    @property
    def found(self) -> bool:
        """Whether the phrase selected anything."""
        return not self.selection.empty


@dataclass(frozen=True)
class Catalog:
    """A vocabulary answered on a field.

    Attributes:
        labels: [N] int32, the index of the phrase that claims each Gaussian, −1 for none.
        entries: one per phrase, in vocabulary order.
        mode: the selection mode used (``auto`` unless told otherwise).
        scored_by: what ordered the claims: ``"confidence"`` (calibrated region confidences)
            or ``"relevancy"`` (where the engine computes no confidence).
    """

    labels: np.ndarray
    entries: tuple[CatalogEntry, ...]
    mode: str
    scored_by: str

    @property
    def phrases(self) -> tuple[str, ...]:
        return tuple(entry.phrase for entry in self.entries)


def catalog_field(
    engine: FieldQuery, phrases: Sequence[str], config: QueryConfig | None = None
) -> Catalog:
    """Answer every phrase (one batch through ``engine``) and label every Gaussian with the
    phrase that claims it most confidently (module docstring: the rule and its ties).

    Args:
        engine: the field's query engine.
        phrases: the vocabulary (:func:`read_vocabulary`); distinct, non-empty.
        config: the selection (default: the engine's, the automatic one unless set).

    Raises:
        InputError: no phrase, an empty phrase, or a phrase given twice.
    """
    phrases = list(phrases)
    if not phrases:
        raise InputError("vocabulary", "give at least one phrase")
    repeated = sorted(phrase for phrase, count in Counter(phrases).items() if count > 1)
    if repeated:
        raise InputError("vocabulary", f"phrases given twice: {repeated}")
    config = engine.config if config is None else config.check()
    selections = engine.select(phrases, config)
    with_confidence = all(s.region_confidence is not None for s in selections if not s.empty)
    regions = engine.regions
    n = len(regions)
    best_score = np.full(n, -np.inf)
    best_size = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
    labels = np.full(n, -1, dtype=np.int32)
    for index, selection in enumerate(selections):
        scores = (
            selection.region_confidence
            if with_confidence and selection.region_confidence is not None
            else tuple(score for _, _, score in selection.regions)
        )
        for (level, region, _), score in zip(selection.regions, scores):
            members = regions.labels[:, level] == region
            size = int(regions.sizes(level)[region])
            wins = members & ((score > best_score) | ((score == best_score) & (size < best_size)))
            best_score[wins] = score
            best_size[wins] = size
            labels[wins] = index
    kept = np.bincount(labels[labels >= 0], minlength=len(phrases))
    entries = tuple(
        CatalogEntry(index, phrase, selection, int(kept[index]))
        for index, (phrase, selection) in enumerate(zip(phrases, selections))
    )
    return Catalog(labels, entries, config.mode, "confidence" if with_confidence else "relevancy")


def _table(catalog: Catalog, files: dict[int, str]) -> str:
    lines = [
        f"Catalog of {len(catalog.entries)} phrases ({catalog.mode} selection; overlaps go to the "
        f"higher {catalog.scored_by}, then the smaller region, then the earlier phrase)",
        "",
        "| label | phrase | found | confidence | Gaussians selected | Gaussians kept | PLY |",
        "|---|---|---|---|---|---|---|",
    ]
    for entry in catalog.entries:
        selection = entry.selection
        confidence = "–" if selection.confidence is None else f"{selection.confidence:.2f}"
        found = "yes" if entry.found else f"no: {selection.reason or 'nothing selected'}"
        phrase, found = (text.replace("|", "\\|") for text in (entry.phrase, found))
        lines.append(
            f"| {entry.index} | {phrase} | {found} | {confidence} | "
            f"{int(selection.gaussians.sum()):,} | {entry.kept:,} | {files.get(entry.index, '–')} |"
        )
    unlabelled = int((catalog.labels < 0).sum())
    lines += ["", f"{unlabelled:,} of {len(catalog.labels):,} Gaussians carry no phrase (−1)."]
    return "\n".join(lines) + "\n"


def _picture_views(
    gaussians: Gaussians,
    cameras: Cameras | None,
    found: list[CatalogEntry],
    raster: RasterConfig,
) -> dict[int, int]:
    """Phrase index → the view (of :data:`PICTURE_VIEWS` spread over ``cameras``) that shows
    most of its selection, for those one of them shows."""
    from thgs.views import best_views

    if cameras is None or not found:
        return {}
    candidates = np.unique(np.linspace(0, len(cameras) - 1, PICTURE_VIEWS).round().astype(int))
    selected = np.stack([entry.selection.gaussians for entry in found], axis=1)
    views = best_views(
        gaussians,
        cameras.select(candidates.tolist()),
        selected,
        scale=PICTURE_CHOICE_SCALE,
        config=raster,
    )
    return {
        entry.index: int(candidates[view])
        for entry, view in zip(found, views.tolist())
        if view >= 0
    }


PICTURE_VIEWS = 12
"""Pictures are drawn in the best of this many views, spread evenly over the scene's cameras
(which also bounds the renders: at most two per view)."""

PICTURE_CHOICE_SCALE = 0.25
"""The views are compared on renders at this fraction of their size (the pictures are drawn
at full size)."""


def _pictures(
    gaussians: Gaussians,
    cameras: Cameras,
    views: dict[int, int],
    entries: list[CatalogEntry],
    raster: RasterConfig,
) -> dict[int, np.ndarray]:
    """Phrase index → its picture, [H, 2W, 3] in [0, 1]: the view beside the same with the
    selection tinted; one scene render and one render of every selection shown per view."""
    from thgs.views import highlighted, scene_image, selection_masks

    pictures = {}
    for view in sorted(set(views.values())):
        shown = [entry for entry in entries if views.get(entry.index) == view]
        camera = cameras.select([view])
        photo, _ = scene_image(gaussians, camera, config=raster)
        selected = np.stack([entry.selection.gaussians for entry in shown], axis=1)
        masks = selection_masks(gaussians, camera, selected, config=raster)
        for column, entry in enumerate(shown):
            tinted = highlighted(photo, masks[..., column])
            pictures[entry.index] = np.concatenate([photo, tinted], axis=1)
    return pictures


def write_catalog(
    out: str | os.PathLike[str],
    catalog: Catalog,
    gaussians: Gaussians,
    engine: FieldQuery,
    *,
    field_name: str,
    cameras: Cameras | None = None,
    raster: RasterConfig = RasterConfig(),
) -> tuple[Path, ...]:
    """Write ``catalog`` into the folder ``out`` (module docstring), all of it or, on any failure
    or interruption, none of it (files are staged, then moved in).

    Args:
        out: the folder (created if missing; files of the same names replaced).
        catalog: from :func:`catalog_field`.
        gaussians: the scene's N Gaussians, in the field's order (the PLY's).
        engine: the engine that answered (its regions size the table).
        field_name: recorded in ``catalog.json``.
        cameras: the views to picture each phrase found in (its best one); None: no pictures.
        raster: the rasterization settings of the pictures (the field's lift's).

    Returns:
        the files written, ``labels.npy`` first.

    Raises:
        InputError: Gaussians of another number than the catalog's labels, or a file that
            cannot be written (named).
    """
    out = Path(out)
    if len(gaussians) != len(catalog.labels):
        raise InputError(
            "gaussians",
            f"the catalog has {len(catalog.labels)} Gaussians, the scene {len(gaussians)}",
        )
    names = unique_names(catalog.phrases, taken=[Path(name).stem for name in CATALOG_FILES])
    files = {
        entry.index: f"{name}.ply" for entry, name in zip(catalog.entries, names) if entry.found
    }
    found = [entry for entry in catalog.entries if entry.index in files]
    views = _picture_views(gaussians, cameras, found, raster)
    pictures = {
        entry.index: f"{name}.png"
        for entry, name in zip(catalog.entries, names)
        if entry.index in views
    }
    extras = dict(gaussians.extras)
    if "label" in extras:
        logger.warning("the scene's PLY has a 'label' property: labels.ply replaces it")
    extras["label"] = catalog.labels.astype(np.int32)
    document: dict[str, Any] = {
        "field": field_name,
        "mode": catalog.mode,
        "overlaps": {
            "rule": f"higher {catalog.scored_by}, then the smaller region, then the earlier phrase",
            "scored_by": catalog.scored_by,
        },
        "gaussians": len(catalog.labels),
        "unlabelled": int((catalog.labels < 0).sum()),
        "phrases": [
            {
                "label": entry.index,
                **entry.selection.to_json(engine.regions),
                "kept": entry.kept,
                **({"ply": files[entry.index]} if entry.index in files else {}),
                **(
                    {"picture": pictures[entry.index], "view": cameras.stems[views[entry.index]]}
                    if cameras is not None and entry.index in pictures
                    else {}
                ),
            }
            for entry in catalog.entries
        ],
    }
    written = (
        [out / name for name in CATALOG_FILES]
        + [out / name for name in files.values()]
        + [out / name for name in pictures.values()]
    )
    created = not out.exists()
    try:
        with atomic_files(written) as staged:
            labels_npy, labels_ply, table_json, table_md = staged[: len(CATALOG_FILES)]
            plys = staged[len(CATALOG_FILES) : len(CATALOG_FILES) + len(files)]
            pngs = staged[len(CATALOG_FILES) + len(files) :]
            np.save(labels_npy, catalog.labels.astype(np.int32), allow_pickle=False)
            write_ply(labels_ply, replace(gaussians, extras=extras))
            write_json(table_json, document)
            table_md.write_text(_table(catalog, files), encoding="utf-8")
            for entry, path in zip(found, plys):
                write_selection_ply(path, gaussians, entry.selection.gaussians)
            pictured = [entry for entry in found if entry.index in pictures]
            if pictured:
                assert cameras is not None
                images = _pictures(gaussians, cameras, views, pictured, raster)
                for entry, path in zip(pictured, pngs):
                    write_map_png(path, images[entry.index])
    except BaseException:
        if created:
            with contextlib.suppress(OSError):  # only if nothing else was put there
                out.rmdir()
        raise
    return tuple(written)
