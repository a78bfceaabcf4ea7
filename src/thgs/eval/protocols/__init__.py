"""The evaluation protocols, one module each, and their registry.

A protocol is one :class:`Protocol` record: the ground truth it reads (a
:class:`GroundTruthSource`, which says where that ground truth lies in a dataset folder), whether
it renders views (needs cameras), how it evaluates (:class:`EvalContext` → results) and its
headline metrics (what ``thgs bench`` tabulates). :func:`thgs.eval.find_ground_truth`,
:func:`thgs.eval.evaluate_dataset`, ``thgs eval`` and ``thgs bench`` read only this registry.

**Adding a protocol is one new module** in this folder that calls :func:`register_source` (if
its ground truth is new) and :func:`register_protocol`, plus its name in :data:`BUILT_IN`
(or, from outside thgs, importing the module before evaluating). The built-in ones, in report
order: ``lerf``, ``lerf-langsplat``, ``lerf-opengaussian`` (LERF-OVS under the THGS, LangSplat
and OpenGaussian rules), ``3dovs``, ``scannet``, ``openhype`` (OpenHype's ScanNet++ objects and
parts), ``hierarchy`` (synthetic scenes).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from thgs.errors import InputError
from thgs.eval.evaluate import ProtocolResult
from thgs.query import FieldQuery
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians

__all__ = [
    "BUILT_IN",
    "EvalContext",
    "GroundTruthSource",
    "Protocol",
    "get_protocol",
    "one_place",
    "protocol_names",
    "register_protocol",
    "register_source",
    "scene_folder",
    "source_names",
    "sources",
]


@dataclass(frozen=True)
class GroundTruthSource:
    """One kind of ground truth and where it lies in a dataset folder.

    Attributes:
        name: its key in :class:`thgs.eval.GroundTruth` and the keyword that gives its path
            explicitly to :func:`thgs.eval.find_ground_truth` (e.g. ``"lerf"``).
        find: the path of this ground truth in a dataset folder, or None when it has none.
        describe: what and where it is, for messages and docs.
        given: the path of this ground truth from a path given explicitly and the scene's name
            (e.g. a folder holding one sub-folder per scene → the scene's); None: the given
            path as it is.
    """

    name: str
    find: Callable[[Path], Path | None]
    describe: str
    given: Callable[[Path, str], Path] | None = None


@dataclass(frozen=True)
class EvalContext:
    """What a protocol evaluates with.

    Attributes:
        engine: the query engine over the segmentation (text → Gaussians).
        gaussians: the N Gaussians; cameras: the scene's cameras (None: none known).
        ground_truth: the path of this protocol's ground truth.
        scene_name: the scene's name (the dataset folder's), e.g. for OpenGaussian's prompts.
        raster: how views are rendered (the field's lifting settings).
        options: protocol options by name (``scannet_level``: the level whose features classify
            ScanNet points).
        progress: ``progress(done, total)`` per scored frame or view.
        shared: ground truth read once and shared by the protocols of one evaluation (the three
            LERF-OVS protocols read the same frames): use :meth:`read`.
    """

    engine: FieldQuery
    gaussians: Gaussians
    cameras: Cameras | None
    ground_truth: Path
    scene_name: str = ""
    raster: RasterConfig = RasterConfig()
    options: dict[str, Any] = field(default_factory=dict)
    progress: Callable[[int, int], None] | None = None
    shared: dict[tuple[str, Path], Any] = field(default_factory=dict)

    def read(self, what: str, reader: Callable[[Path], Any]) -> Any:
        """``reader(ground_truth)``, read once per evaluation and kept under ``what``."""
        key = (what, self.ground_truth)
        if key not in self.shared:
            self.shared[key] = reader(self.ground_truth)
        return self.shared[key]


@dataclass(frozen=True)
class Protocol:
    """One evaluation protocol.

    Attributes:
        name: as named on the command line and in reports (e.g. ``"3dovs"``).
        summary: one line for ``thgs eval --help``.
        source: the name of the :class:`GroundTruthSource` it reads.
        needs_cameras: whether it renders views (refused for a scene without cameras).
        headline: ``(result name, metric)`` pairs that summarize it (``thgs bench``'s columns;
            a result name differs from the protocol's where one protocol gives several results,
            e.g. ScanNet's ``scannet-all``).
        evaluate: the results of the protocol on one scene.
    """

    name: str
    summary: str
    source: str
    needs_cameras: bool
    headline: tuple[tuple[str, str], ...]
    evaluate: Callable[[EvalContext], Sequence[ProtocolResult]]


logger = logging.getLogger(__name__)

_SOURCES: dict[str, GroundTruthSource] = {}
_PROTOCOLS: dict[str, Protocol] = {}


def one_place(
    dataset: Path,
    candidates: Sequence[Path],
    holds: Callable[[Path], bool],
    what: str,
    choose: str,
) -> Path | None:
    """The one candidate folder that ``holds`` ground truth, or None when none does
    (``GroundTruthSource.find``).

    Args:
        dataset: the dataset folder, for the message.
        candidates: the places to look, in order (the same folder twice counts once).
        holds: whether a folder holds this ground truth.
        what: the ground truth, for the message (e.g. "LERF-OVS labels (frame_*.json)").
        choose: how the user decides, for the message (e.g. "with --labels (lerf= in
            Python)").

    Raises:
        InputError: two different folders hold it (the message names both).
    """
    found: dict[Path, Path] = {}
    for candidate in candidates:
        if holds(candidate):
            found.setdefault(candidate.resolve(), candidate)
    if len(found) > 1:
        raise InputError(
            dataset,
            f"{what} in two places: "
            + " and ".join(map(str, found.values()))
            + f"; choose one {choose}",
        )
    return next(iter(found.values()), None)


def scene_folder(given: Path, scene: str, container: str, what: str, files: str, flag: str) -> Path:
    """A scene's ground-truth folder from a folder given for it (``GroundTruthSource.given``):
    the folder itself when it holds ``*.json`` files, else its ``<scene>/`` sub-folder (the
    folder of every scene's), else ``<container>/<scene>/`` in it (the benchmark's root).

    Args:
        given: the path given (a file is returned as it is).
        scene: the scene's name (its dataset folder's).
        container: the folder of every scene's ground truth in the benchmark's root.
        what: the files looked for, for the message (e.g. "LERF-OVS label files (frame_*.json)").
        files: their pattern, for the message (e.g. "frame_*.json").
        flag: the flag that names the folder, for the message.

    Raises:
        InputError: none holds ``*.json`` files (the message lists the sub-folders there are).
    """
    if not given.is_dir() or _has_json(given):
        return given
    for inside in (given / scene, given / container / scene):
        if _has_json(inside):
            logger.info("ground truth of %s: %s", scene, inside)
            return inside
    folders = sorted(child.name for child in given.iterdir() if child.is_dir())
    holds = f"its folders: {', '.join(folders)}" if folders else "it holds no folder"
    raise InputError(
        given,
        f"holds no {what}, nor {scene}/ or {container}/{scene}/ with them ({holds}; {scene!r} is "
        f"the dataset folder's name); pass the folder of the scene's {files} with {flag}",
    )


def _has_json(folder: Path) -> bool:
    return folder.is_dir() and any(
        path.name.endswith(".json") and not path.name.startswith(".") for path in folder.iterdir()
    )


def register_source(source: GroundTruthSource) -> GroundTruthSource:
    """Add a kind of ground truth (its name must be new)."""
    if source.name in _SOURCES:
        raise ValueError(f"ground-truth source {source.name!r} is already registered")
    _SOURCES[source.name] = source
    return source


def register_protocol(protocol: Protocol) -> Protocol:
    """Add a protocol (its name must be new, its source registered); reports list protocols in
    registration order."""
    if protocol.name in _PROTOCOLS:
        raise ValueError(f"protocol {protocol.name!r} is already registered")
    if protocol.source not in _SOURCES:
        raise ValueError(f"protocol {protocol.name!r} reads an unknown source {protocol.source!r}")
    _PROTOCOLS[protocol.name] = protocol
    return protocol


def protocol_names() -> tuple[str, ...]:
    """Every registered protocol, in report order."""
    return tuple(_PROTOCOLS)


def get_protocol(name: str) -> Protocol:
    """The protocol called ``name``.

    Raises:
        InputError: no such protocol (the message lists them).
    """
    if name not in _PROTOCOLS:
        raise InputError("protocol", f"unknown {name!r}; choose from {', '.join(_PROTOCOLS)}")
    return _PROTOCOLS[name]


def source_names() -> tuple[str, ...]:
    """Every registered kind of ground truth."""
    return tuple(_SOURCES)


def sources() -> tuple[GroundTruthSource, ...]:
    """Every registered kind of ground truth, in registration order."""
    return tuple(_SOURCES.values())


BUILT_IN = (
    "lerf",
    "lerf_langsplat",
    "lerf_opengaussian",
    "three_dovs",
    "scannet",
    "openhype",
    "hierarchy",
)
"""The built-in protocol modules, imported (so registered) in report order."""

for _module in BUILT_IN:
    importlib.import_module(f"{__name__}.{_module}")
