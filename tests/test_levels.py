"""The one hierarchy type: RegionLevels (construction, accessors, select, check) and the ground
truth held in it (Hierarchy.from_subparts, select, the file round trip)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.eval.ground_truth import Hierarchy, read_hierarchy, write_hierarchy
from thgs.hierarchy import LEVEL_NAMES, RegionLevels

# 8 Gaussians: superpoints 0..5 → sub-parts 0..3 → parts 0..2 → objects 0..1
LABELS = np.array(
    [
        [0, 0, 0, 0],
        [0, 0, 0, 0],
        [1, 0, 0, 0],
        [2, 1, 0, 0],
        [3, 2, 1, 1],
        [4, 2, 1, 1],
        [5, 3, 2, 1],
        [5, 3, 2, 1],
    ],
    dtype=np.int32,
)


def test_from_labels_derives_parents_and_counts():
    levels = RegionLevels.from_labels(LABELS)
    assert levels.nested and len(levels) == 8
    assert levels.counts == (6, 4, 3, 2)
    expected = ([0, 0, 1, 2, 2, 3], [0, 0, 1, 2], [0, 1, 1])
    for parent, want in zip(levels.parents, expected):
        assert parent.dtype == np.int32
        np.testing.assert_array_equal(parent, want)
    np.testing.assert_array_equal(levels.sizes(1), [3, 1, 2, 2])
    assert levels.parent(1, 3) == 2 and levels.parent(2, 2) == 1
    np.testing.assert_array_equal(levels.children(3, 1), [1, 2])
    np.testing.assert_array_equal(levels.members(2, 1), [4, 5])
    assert LEVEL_NAMES == ("superpoint", "subpart", "part", "object")


def test_levels_that_do_not_nest():
    crossed = LABELS.copy()
    crossed[:, 2] = np.arange(8) % 2  # parts across sub-parts
    with pytest.raises(InputError, match="not nested: region 0 lies in several regions"):
        RegionLevels.from_labels(crossed)
    independent = RegionLevels.from_labels(crossed, nested=False)
    assert not independent.nested and independent.counts == (6, 4, 2, 2)
    np.testing.assert_array_equal(independent.sizes(2), [4, 4])
    with pytest.raises(InputError, match="do not nest"):
        independent.parent(1, 0)
    with pytest.raises(InputError, match="do not nest"):
        independent.children(2, 0)
    with pytest.raises(InputError, match=r"must be \[N, 4\] integers"):
        RegionLevels.from_labels(LABELS[:, :3])


def _brute_select(labels: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Each level's kept ids renumbered by first appearance in id order (the documented order)."""
    out = np.empty((keep.size, 4), dtype=np.int32)
    for k in range(4):
        ids = sorted(set(labels[keep, k].tolist()))
        out[:, k] = [ids.index(v) for v in labels[keep, k]]
    return out


@pytest.mark.parametrize("keep", [[0, 1, 4, 5], [7, 3, 0], [2, 6], list(range(8))])
def test_select_keeps_the_levels_consistent(keep):
    levels = RegionLevels.from_labels(LABELS)
    index = np.array(keep)
    subset, kept = levels.select(index)
    np.testing.assert_array_equal(subset.labels, _brute_select(LABELS, index))
    subset.check("subset")  # contiguous and nested
    for k in range(4):
        # each new region's old id gives back the Gaussians' old labels
        np.testing.assert_array_equal(kept[k][subset.labels[:, k]], LABELS[index, k])
        assert subset.counts[k] == kept[k].size
    for k in (1, 2, 3):
        np.testing.assert_array_equal(
            subset.labels[:, k], subset.parents[k - 1][subset.labels[:, k - 1]]
        )
    mask = np.zeros(8, bool)
    mask[index] = True
    by_mask, _ = levels.select(mask)
    np.testing.assert_array_equal(by_mask.labels, _brute_select(LABELS, np.sort(index)))


def test_select_refuses_bad_subsets():
    levels = RegionLevels.from_labels(LABELS)
    with pytest.raises(InputError, match=r"a mask must be \[N\] = \[8\]"):
        levels.select(np.ones(7, bool))
    with pytest.raises(InputError, match=r"indices must be in 0\.\.7"):
        levels.select(np.array([0, 8]))
    with pytest.raises(InputError, match="bool mask or"):
        levels.select(np.array([0.5]))


CHECKS = {
    "label out of range": (
        lambda v: dataclasses.replace(v, counts=(6, 4, 3, 1)),
        "parents[2] must be level-3 ids in 0..0, region 1 has 1",
    ),
    "not contiguous": (
        lambda v: dataclasses.replace(v, counts=(7, 4, 3, 2), parents=None),
        "level 0 ids are not contiguous: 1 of 7 regions have no Gaussian (first: region 6)",
    ),
    "unlabelled not allowed": (
        lambda v: dataclasses.replace(v, labels=np.where(np.arange(8)[:, None] == 0, -1, LABELS)),
        "labels[:, 0] must be in 0..5, Gaussian 0 has -1",
    ),
    "parents not nested": (
        lambda v: dataclasses.replace(
            v, parents=(v.parents[0], np.array([0, 1, 1, 2], np.int32), v.parents[2])
        ),
        "labels are not nested between levels 1 and 2: 1 Gaussians disagree with parents[1]",
    ),
}


@pytest.mark.parametrize("case", CHECKS, ids=list(CHECKS))
def test_check_names_each_broken_invariant(case):
    edit, message = CHECKS[case]
    with pytest.raises(InputError, match=re.escape(message)):
        edit(RegionLevels.from_labels(LABELS)).check("mine")


def test_unlabelled_gaussians_are_none_at_every_level():
    labels = LABELS.copy()
    labels[0] = -1
    levels = RegionLevels(labels, RegionLevels.from_labels(LABELS).parents, (6, 4, 3, 2))
    levels.check(unlabelled=True)
    np.testing.assert_array_equal(levels.sizes(1), [2, 1, 2, 2])
    labels[1, 3] = -1
    with pytest.raises(InputError, match="labelled at some levels but not others"):
        dataclasses.replace(levels, labels=labels).check(unlabelled=True)


# ground truth in the one numbering


def _hierarchy() -> Hierarchy:
    names = (("rim", "wall", "handle", "ear"), ("body", "handle", "head"), ("mug", "bear"))
    subparts = np.array([0, 0, 1, 2, -1, 3, 3, 1])
    return Hierarchy.from_subparts(subparts, [0, 0, 1, 2], [0, 0, 1], names)


def test_ground_truth_uses_the_fields_level_numbers(tmp_path):
    hierarchy = _hierarchy()
    np.testing.assert_array_equal(
        hierarchy.labels,
        [
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [1, 1, 0, 0],
            [2, 2, 1, 0],
            [-1, -1, -1, -1],
            [3, 3, 2, 1],
            [3, 3, 2, 1],
            [1, 1, 0, 0],
        ],
    )
    assert list(hierarchy.level_names(3)) == ["mug"] * 4 + [None] + ["bear"] * 2 + ["mug"]
    assert hierarchy.level_names(1)[3] == "handle"
    with pytest.raises(InputError, match=r"level must be in 1\.\.3 here, got 0"):
        hierarchy.level_names(0)
    path = tmp_path / "truth.safetensors"
    write_hierarchy(path, hierarchy)
    back = read_hierarchy(path)
    np.testing.assert_array_equal(back.labels, hierarchy.labels)
    assert back.names == hierarchy.names
    for mine, theirs in zip(back.levels.parents, hierarchy.levels.parents):
        np.testing.assert_array_equal(mine, theirs)


def test_ground_truth_select_drops_empty_nodes_with_their_names():
    hierarchy = _hierarchy()
    subset = hierarchy.select(np.array([5, 6, 3]))
    assert subset.names == {1: ("handle", "ear"), 2: ("handle", "head"), 3: ("mug", "bear")}
    assert list(subset.level_names(1)) == ["ear", "ear", "handle"]
    assert list(subset.level_names(3)) == ["bear", "bear", "mug"]


def test_ground_truth_refuses_inconsistent_trees():
    names = (("a", "b"), ("p",), ("o",))
    with pytest.raises(InputError, match="parent arrays do not match"):
        Hierarchy.from_subparts(np.array([0, 1]), [0], [0], names)
    with pytest.raises(InputError, match=r"part parents must be object ids in 0\.\.0"):
        Hierarchy.from_subparts(np.array([0, 1]), [0, 0], [1], names)
    with pytest.raises(InputError, match=r"subpart ids outside \[-1, 2\)"):
        Hierarchy.from_subparts(np.array([0, 2]), [0, 0], [0], names)
    with pytest.raises(InputError, match="2 subpart names for 3 nodes"):
        hierarchy = Hierarchy.from_subparts(np.array([0, 1]), [0, 0], [0], names)
        counts = (3, 3, 1, 1)
        levels = dataclasses.replace(
            hierarchy.levels,
            counts=counts,
            parents=(np.arange(3, dtype=np.int32), np.zeros(3, np.int32), np.zeros(1, np.int32)),
        )
        dataclasses.replace(hierarchy, levels=levels).check()
