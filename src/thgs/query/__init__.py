"""Open-vocabulary queries of a semantic field (design §4.8): relevancy and region selection.

The relevancy of a region with unit feature φ for a query embedding q, against the canonical
phrases c_i ("object", "things", "stuff", "texture"), is LERF's

    rel(φ, q) = min_i exp(t φ·q) / (exp(t φ·q) + exp(t φ·c_i)),   t = 10,

which equals ``min_i σ(t (φ·q − φ·c_i))`` and is computed in that stable form. It lies in
(0, 1); 0.5 means "no more like the query than like a generic phrase". Regions that no view saw
have no feature and score 0, so they are never selected.

Four ways to turn relevancies into a selection (:class:`QueryConfig`):

- ``auto`` (the default) — decided from the query's own scores and the hierarchy, with no
  per-scene setting (:func:`select_auto`, docs/query.md). Cosines are read on features centred
  on the scene's mean feature, which removes what every region shares (CLIP's image embeddings
  share one direction) and makes them comparable across embedding spaces. Abstain when the
  best region is no closer to the query than ordinary names get to this scene (its cosine
  ``min_score`` standard deviations above the null of :data:`thgs.confidence.NULL_PHRASES`;
  the selection says why). Otherwise descend the hierarchy from every object: a region at
  least as close as ``best − extent · (best − median)`` is taken whole unless a region inside
  it is closer by more than ``descend`` of that spread — then the query is about a part of it,
  and the descent goes on into the children that come near the best one. One part, an object
  split over several regions, a table's four legs, two mugs: the regions named like the query,
  at the level where they are so named, and not the object around a part that only looks
  like it.
- ``paper`` — the paper's evaluation: the 3 most relevant regions of level 2 and the 3 of
  level 3 are pooled, the 3 best of those six are kept, no threshold. Something is always
  selected, even for a query about nothing in the scene.
- ``level`` — the ``top`` most relevant regions of one level: "the best object", "the best part".
- ``threshold`` — every region of one level whose relevancy reaches a threshold, so a query about
  nothing in the scene selects nothing, and an object split into several regions is selected
  whole. The default threshold depends on the embedding space (:func:`default_threshold`).

The selected Gaussians are the union of the chosen regions' members. :class:`FieldQuery` is the
one query engine: it runs batches of queries on a field or on any :class:`Regions` (levels that
need not nest), with text embeddings and results cached per text, for the CLI, the viewer and
every evaluation protocol.

The package's modules, one concern each: :mod:`thgs.query.relevancy` (the formula),
:mod:`thgs.query.config` (:class:`QueryConfig`), :mod:`thgs.query.regions` (what is queried),
:mod:`thgs.query.rules` (the selection rules) and :mod:`thgs.query.engine` (:class:`FieldQuery`).
"""

from thgs.query.config import QueryConfig
from thgs.query.engine import FieldQuery
from thgs.query.regions import Regions, small_region_size
from thgs.query.relevancy import CANONICAL_PHRASES, default_threshold, relevancy
from thgs.query.rules import (
    AutoChoice,
    Selection,
    abstain_reason,
    select,
    select_auto,
    select_paper,
    unselectable_reason,
)

__all__ = [
    "CANONICAL_PHRASES",
    "AutoChoice",
    "FieldQuery",
    "QueryConfig",
    "Regions",
    "Selection",
    "abstain_reason",
    "default_threshold",
    "relevancy",
    "select",
    "select_auto",
    "select_paper",
    "small_region_size",
    "unselectable_reason",
]
