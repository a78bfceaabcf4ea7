"""The field's hierarchy as a scene graph: every region of every level, what it is part of and
made of, where it is, what it may be called, and which regions of its level it touches.

:func:`scene_graph` makes a :class:`SceneGraph` from a field and its scene's Gaussians;
:func:`write_scene_graph` writes it as JSON (the layout of ``schemas/scene_graph.schema.json``,
a JSON Schema shipped with the package: :func:`scene_graph_schema`), and
:func:`read_scene_graph` reads such a file back, typed and checked. For every node:

- ``id``: ``"<level name>-<region>"`` (``"object-3"``, ``"part-12"``, ``"subpart-7"``,
  ``"superpoint-40"``): the field's own region ids, so the same field gives the same ids on every
  run;
- ``parent`` and ``children``: the node one level up and the nodes one level down;
- ``gaussians``, ``centroid`` (the mean of the member Gaussians' centres), ``box`` (axis-aligned:
  ``min``, ``max``) and ``oriented_box`` (the principal axes of the members' centres: ``center``,
  ``axes`` as three unit rows, longest first, right-handed, each with its largest component
  positive; ``half_extents`` along them), all in the scene's world frame and units (those of the
  Gaussians' means in the PLY);
- ``names``: with a vocabulary, the best phrases for the region (levels 1–3, seen regions), most
  confident first, each with its calibrated confidence
  (:meth:`thgs.query.FieldQuery.confidence`) and centred cosine.

Edges join two regions of one level that touch: Gaussians of the two that are among each
other's nearest neighbours by position (the field's KNN graph settings — ``k`` and the radius —
with colour left out). ``contacts`` counts those neighbour pairs; ``shares`` is, for each of the
two regions, the fraction of its Gaussians with a neighbour in the other.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from thgs._json import load_json
from thgs.errors import InputError
from thgs.export import write_json
from thgs.field import SemanticField
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.scene import Gaussians

__all__ = [
    "SCHEMA_VERSION",
    "GraphEdge",
    "GraphName",
    "GraphNode",
    "OrientedBox",
    "SceneGraph",
    "node_id",
    "read_scene_graph",
    "scene_graph",
    "scene_graph_schema",
    "write_scene_graph",
]

logger = logging.getLogger(__name__)

SCHEMA_VERSION = 1
"""The layout :func:`write_scene_graph` writes (``"version"`` in the file)."""

_FORMAT = "thgs.scene_graph"


def node_id(level: int, region: int) -> str:
    """The id of region ``region`` of level ``level`` (0 superpoints … 3 objects)."""
    return f"{LEVEL_NAMES[level]}-{region}"


@dataclass(frozen=True)
class GraphName:
    """A phrase of the vocabulary for a region.

    Attributes:
        text: the phrase.
        confidence: the calibrated probability that the region belongs to what it names; None
            when the scene has no null to calibrate against.
        cosine: the centred cosine of the region's feature with the phrase.
    """

    text: str
    confidence: float | None
    cosine: float


@dataclass(frozen=True)
class OrientedBox:
    """A box along the principal axes of a region's Gaussian centres (world frame, scene units).

    Attributes:
        center: [3] the box's centre.
        axes: three unit [3] rows, longest extent first, right-handed.
        half_extents: [3] half the box's size along each axis.
    """

    center: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...]
    half_extents: tuple[float, float, float]


@dataclass(frozen=True)
class GraphNode:
    """One region of one level (see the module docstring).

    Attributes:
        id: ``"<level name>-<region>"``.
        level: 0 superpoint, 1 sub-part, 2 part, 3 object.
        region: the region's id in the field at that level.
        parent: the containing region's id (None for objects).
        children: the ids of the regions one level down inside it (none for superpoints).
        gaussians: how many Gaussians it holds.
        seen: whether a view gave it a feature (superpoints have none: False).
        centroid: [3] mean of its Gaussians' centres.
        box_min, box_max: [3] its axis-aligned box.
        oriented_box: its box along its principal axes.
        names: the vocabulary's best phrases, most confident first (empty without one).
    """

    id: str
    level: int
    region: int
    parent: str | None
    children: tuple[str, ...]
    gaussians: int
    seen: bool
    centroid: tuple[float, float, float]
    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]
    oriented_box: OrientedBox
    names: tuple[GraphName, ...] = ()


@dataclass(frozen=True)
class GraphEdge:
    """Two regions of one level that touch.

    Attributes:
        level: their level.
        a, b: their ids, ``a`` of the lower region id.
        contacts: neighbour pairs with one Gaussian in each.
        shares: the fraction of ``a``'s and of ``b``'s Gaussians with a neighbour in the other.
    """

    level: int
    a: str
    b: str
    contacts: int
    shares: tuple[float, float]


@dataclass(frozen=True)
class SceneGraph:
    """A field's hierarchy as a graph (module docstring).

    Attributes:
        field: the field file it was made from (as given).
        space: the field's embedding space.
        gaussians: N.
        vocabulary: the phrases names were chosen from (empty: no names).
        neighbours: k of the neighbour graph that decided which regions touch.
        nodes: every region of levels 0–3, by level, then region id.
        edges: every touching pair of every level, by level, then ids.
    """

    field: str
    space: str
    gaussians: int
    vocabulary: tuple[str, ...]
    neighbours: int
    nodes: tuple[GraphNode, ...]
    edges: tuple[GraphEdge, ...]

    def node(self, id: str) -> GraphNode:
        """The node named ``id``.

        Raises:
            KeyError: no such node.
        """
        for node in self.nodes:
            if node.id == id:
                return node
        raise KeyError(id)

    def to_json(self) -> dict[str, Any]:
        """The file's JSON document (``schemas/scene_graph.schema.json``)."""
        return {
            "format": _FORMAT,
            "version": SCHEMA_VERSION,
            "field": self.field,
            "space": self.space,
            "gaussians": self.gaussians,
            "frame": "the scene's world frame and units (the Gaussians' means)",
            "levels": list(LEVEL_NAMES),
            "vocabulary": list(self.vocabulary),
            "neighbours": self.neighbours,
            "nodes": [_node_json(node) for node in self.nodes],
            "edges": [
                {
                    "level": edge.level,
                    "a": edge.a,
                    "b": edge.b,
                    "contacts": edge.contacts,
                    "shares": list(edge.shares),
                }
                for edge in self.edges
            ],
        }


def _node_json(node: GraphNode) -> dict[str, Any]:
    box = node.oriented_box
    return {
        "id": node.id,
        "level": node.level,
        "region": node.region,
        "parent": node.parent,
        "children": list(node.children),
        "gaussians": node.gaussians,
        "seen": node.seen,
        "centroid": list(node.centroid),
        "box": {"min": list(node.box_min), "max": list(node.box_max)},
        "oriented_box": {
            "center": list(box.center),
            "axes": [list(axis) for axis in box.axes],
            "half_extents": list(box.half_extents),
        },
        "names": [
            {"text": name.text, "confidence": name.confidence, "cosine": name.cosine}
            for name in node.names
        ],
    }


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


def oriented_box(points: np.ndarray) -> OrientedBox:
    """The box of ``points`` ([M, 3], M ≥ 1) along their principal axes: longest extent first
    (ties: the axis of larger variance), the first two axes with their largest component
    positive, the third their cross product."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes = vectors.T[::-1]  # descending variance
    projected = points @ axes.T
    extents = projected.max(axis=0) - projected.min(axis=0)
    axes = axes[np.argsort(-extents, kind="stable")].copy()
    for axis in axes[:2]:
        if axis[np.argmax(np.abs(axis))] < 0:
            axis *= -1
    axes[2] = np.cross(axes[0], axes[1])
    projected = points @ axes.T
    low, high = projected.min(axis=0), projected.max(axis=0)
    return OrientedBox(
        _triple(((low + high) / 2) @ axes),
        tuple(_triple(axis) for axis in axes),
        _triple((high - low) / 2),
    )


def _touching(
    labels: np.ndarray, neighbors: np.ndarray, sizes: np.ndarray, level: int
) -> list[GraphEdge]:
    """The edges of one level from the [N, K] neighbour table (−1 missing)."""
    n = len(labels)
    rows = np.repeat(np.arange(n), neighbors.shape[1])
    cols = neighbors.ravel()
    present = cols >= 0
    rows, cols = rows[present], cols[present].astype(np.int64)
    across = labels[rows] != labels[cols]
    rows, cols = rows[across], cols[across]
    if rows.size == 0:
        return []
    # each undirected Gaussian pair once
    pairs = np.unique(np.stack([np.minimum(rows, cols), np.maximum(rows, cols)], axis=1), axis=0)
    ra, rb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    low, high = np.minimum(ra, rb), np.maximum(ra, rb)
    count = int(labels.max()) + 1
    keys, contacts = np.unique(low.astype(np.int64) * count + high, return_counts=True)
    # Gaussian i has a neighbour in region r: each (i, r) once, both directions of every edge
    gaussian = np.concatenate([rows, cols])
    other = np.concatenate([labels[cols], labels[rows]])
    touched = np.unique(gaussian.astype(np.int64) * count + other)
    owner = labels[touched // count].astype(np.int64)
    reached = np.unique(owner * count + touched % count, return_counts=True)
    reach = dict(zip(reached[0].tolist(), reached[1].tolist()))
    edges = []
    for key, contact in zip(keys.tolist(), contacts.tolist()):
        a, b = divmod(key, count)
        edges.append(
            GraphEdge(
                level,
                node_id(level, a),
                node_id(level, b),
                int(contact),
                (reach[a * count + b] / int(sizes[a]), reach[b * count + a] / int(sizes[b])),
            )
        )
    return edges


def scene_graph(
    field: SemanticField,
    gaussians: Gaussians,
    *,
    engine=None,
    vocabulary: Sequence[str] = (),
    names: int = 3,
    field_name: str = "",
) -> SceneGraph:
    """The scene graph of ``field`` (module docstring).

    Args:
        field: the semantic field.
        gaussians: the N Gaussians it was built on (their centres place the nodes).
        engine: the field's :class:`thgs.query.FieldQuery` (needed with a vocabulary).
        vocabulary: phrases to name regions with; empty: no names.
        names: how many phrases per region (the most confident).
        field_name: recorded in the graph.

    Raises:
        InputError: Gaussians of another number than the field's, a vocabulary without an
            engine, or ``names`` < 1.
    """
    from thgs.field_config import recorded_config
    from thgs.graph.knn import nearest_neighbors

    if len(gaussians) != len(field):
        raise InputError(
            "gaussians", f"the field has {len(field)} Gaussians, the scene {len(gaussians)}"
        )
    if vocabulary and engine is None:
        raise InputError("vocabulary", "naming regions needs the field's query engine")
    if names < 1:
        raise InputError("names", f"must be ≥ 1, got {names}")
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    try:
        graph = recorded_config(field).superpoints.graph
    except InputError as error:
        from thgs.graph import GraphConfig

        logger.warning("%s; the default neighbour graph decides what touches", error)
        graph = GraphConfig()
    k = min(graph.k, max(len(field) - 1, 1))
    _, index = nearest_neighbors(means, k + 1, graph.radius)
    neighbors = np.where(index < len(field), index, -1)
    neighbors = np.where(neighbors == np.arange(len(field))[:, None], -1, neighbors)

    scored: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if vocabulary:
        for level in (1, 2, 3):
            cosines = engine.centred_similarity(list(vocabulary), level)
            confidence = engine.confidence(list(vocabulary), level)
            scored[level] = (cosines, confidence)

    nodes: list[GraphNode] = []
    edges: list[GraphEdge] = []
    for level in range(4):
        labels = field.labels[:, level]
        sizes = field.sizes(level)
        order = np.argsort(labels, kind="stable")
        groups = np.split(order, np.cumsum(sizes)[:-1])
        children: list[list[str]] = [[] for _ in range(len(sizes))]
        if level > 0:
            for child, parent in enumerate(field.parents[level - 1].tolist()):
                children[parent].append(node_id(level - 1, child))
        for region, members in enumerate(groups):
            points = means[members]
            parent = None if level == 3 else node_id(level + 1, int(field.parents[level][region]))
            seen = level > 0 and bool(field.seen[level - 1][region])
            nodes.append(
                GraphNode(
                    id=node_id(level, region),
                    level=level,
                    region=region,
                    parent=parent,
                    children=tuple(children[region]),
                    gaussians=int(sizes[region]),
                    seen=seen,
                    centroid=_triple(points.mean(axis=0)),
                    box_min=_triple(points.min(axis=0)),
                    box_max=_triple(points.max(axis=0)),
                    oriented_box=oriented_box(points),
                    names=_names(scored, level, region, vocabulary, names) if seen else (),
                )
            )
        edges += _touching(labels, neighbors, sizes, level)
    return SceneGraph(
        field_name, field.space, len(field), tuple(vocabulary), k, tuple(nodes), tuple(edges)
    )


def _names(
    scored: dict[int, tuple[np.ndarray, np.ndarray]],
    level: int,
    region: int,
    vocabulary: Sequence[str],
    count: int,
) -> tuple[GraphName, ...]:
    if level not in scored:
        return ()
    cosines, confidence = scored[level]
    cosine, chance = cosines[:, region], confidence[:, region]
    rank = np.nan_to_num(chance, nan=-1.0)
    best = np.lexsort((np.arange(len(vocabulary)), -cosine, -rank))[:count]
    return tuple(
        GraphName(
            vocabulary[i],
            None if math.isnan(chance[i]) else float(chance[i]),
            float(cosine[i]),
        )
        for i in best
    )


def scene_graph_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a scene graph file."""
    text = resources.files("thgs").joinpath("schemas/scene_graph.schema.json").read_text("utf-8")
    return json.loads(text)


def write_scene_graph(path: str | os.PathLike[str], graph: SceneGraph) -> None:
    """Write ``graph`` as JSON, atomically.

    Raises:
        InputError: ``path`` is a folder, or cannot be written (named).
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder; name the graph's JSON file, e.g. graph.json")
    write_json(path, graph.to_json())


def read_scene_graph(path: str | os.PathLike[str]) -> SceneGraph:
    """Read a file written by :func:`write_scene_graph`, checked against the schema.

    Raises:
        InputError: naming the file: missing, not JSON, not a scene graph, of a newer version,
            or not following the schema (the first problem and where it is).
    """
    import jsonschema

    path = Path(path)
    document = load_json(path)
    if not isinstance(document, dict) or document.get("format") != _FORMAT:
        raise InputError(path, "not a thgs scene graph (no 'format': 'thgs.scene_graph')")
    version = document.get("version")
    if isinstance(version, int) and not isinstance(version, bool) and version > SCHEMA_VERSION:
        raise InputError(
            path, f"written by a newer thgs (version {version}), this one reads {SCHEMA_VERSION}"
        )
    problem = jsonschema.exceptions.best_match(
        jsonschema.Draft202012Validator(scene_graph_schema()).iter_errors(document)
    )
    if problem is not None:
        where = "/".join(str(part) for part in problem.absolute_path) or "the document"
        raise InputError(
            path, f"does not follow the scene graph schema at {where}: {problem.message}"
        )
    nodes = tuple(
        GraphNode(
            id=node["id"],
            level=node["level"],
            region=node["region"],
            parent=node["parent"],
            children=tuple(node["children"]),
            gaussians=node["gaussians"],
            seen=node["seen"],
            centroid=tuple(node["centroid"]),
            box_min=tuple(node["box"]["min"]),
            box_max=tuple(node["box"]["max"]),
            oriented_box=OrientedBox(
                tuple(node["oriented_box"]["center"]),
                tuple(tuple(axis) for axis in node["oriented_box"]["axes"]),
                tuple(node["oriented_box"]["half_extents"]),
            ),
            names=tuple(
                GraphName(name["text"], name["confidence"], name["cosine"])
                for name in node["names"]
            ),
        )
        for node in document["nodes"]
    )
    edges = tuple(
        GraphEdge(edge["level"], edge["a"], edge["b"], edge["contacts"], tuple(edge["shares"]))
        for edge in document["edges"]
    )
    return SceneGraph(
        document["field"],
        document["space"],
        document["gaussians"],
        tuple(document["vocabulary"]),
        document["neighbours"],
        nodes,
        edges,
    )
