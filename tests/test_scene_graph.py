"""The scene graph (thgs.scene_graph, ``thgs export --graph``): nodes and edges against hand
computations and brute-force references, the JSON Schema, the loader, stable ids, bad input."""

from __future__ import annotations

import itertools
import json
import re

import jsonschema
import numpy as np
import pytest
import torch

from conftest import random_gaussians, run_cli
from test_field import mug_field
from thgs.errors import InputError
from thgs.scene_graph import (
    node_id,
    oriented_box,
    read_scene_graph,
    scene_graph,
    scene_graph_schema,
    write_scene_graph,
)


def _mug_gaussians():
    """Six Gaussians of the mug of docs/field.md at hand-placed centres: the rim (0, 1), the
    wall (2, 3), the handle (4, 5)."""
    gaussians = random_gaussians(6, seed=1)
    means = torch.tensor(
        [[0, 0, 1], [0.1, 0, 1], [0, 0, 0.5], [0.1, 0, 0.5], [0.3, 0, 0.6], [0.4, 0, 0.7]],
        dtype=gaussians.means.dtype,
    )
    from dataclasses import replace

    return replace(gaussians, means=means)


def test_an_oriented_box_along_known_axes():
    """A 4 × 2 × 1 grid of points turned about z by 30°: the box finds those axes."""
    angle = np.radians(30)
    turn = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    grid = np.array(list(itertools.product([-2, 2], [-1, 1], [-0.5, 0.5])), dtype=float)
    points = grid @ turn.T + np.array([1.0, 2.0, 3.0])
    box = oriented_box(points)
    np.testing.assert_allclose(box.center, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(box.half_extents, [2, 1, 0.5], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.array(box.axes)), np.abs(turn.T), atol=1e-12)
    axes = np.array(box.axes)
    assert axes[0][np.argmax(np.abs(axes[0]))] > 0 and axes[1][np.argmax(np.abs(axes[1]))] > 0
    np.testing.assert_allclose(np.cross(axes[0], axes[1]), axes[2], atol=1e-12)
    projected = (points - box.center) @ axes.T  # every point inside the box
    assert (np.abs(projected) <= np.array(box.half_extents) + 1e-12).all()


def test_a_single_point_has_an_empty_box():
    box = oriented_box(np.array([[1.0, 2.0, 3.0]]))
    assert box.center == (1.0, 2.0, 3.0) and box.half_extents == (0.0, 0.0, 0.0)


def _reference_edges(labels, neighbors, level):
    """Every pair of regions, by a plain loop over Gaussian pairs."""
    pairs, reach = set(), set()
    for i, row in enumerate(neighbors):
        for j in row:
            if j >= 0 and labels[i] != labels[j]:
                pairs.add((min(i, j), max(i, j)))
                reach.add((i, labels[j]))
                reach.add((j, labels[i]))
    edges = {}
    sizes = np.bincount(labels)
    for i, j in pairs:
        a, b = sorted((labels[i], labels[j]))
        edges[(a, b)] = edges.get((a, b), 0) + 1
    return {
        (node_id(level, a), node_id(level, b)): (
            count,
            sum(1 for g, r in reach if labels[g] == a and r == b) / sizes[a],
            sum(1 for g, r in reach if labels[g] == b and r == a) / sizes[b],
        )
        for (a, b), count in edges.items()
    }


def test_the_mug_graph_by_hand():
    field = mug_field()
    graph = scene_graph(field, _mug_gaussians(), field_name="mug.thgs")
    assert [node.id for node in graph.nodes] == [
        "superpoint-0",
        "superpoint-1",
        "superpoint-2",
        "superpoint-3",
        "subpart-0",
        "subpart-1",
        "subpart-2",
        "part-0",
        "part-1",
        "object-0",
    ]
    handle = graph.node("part-1")
    assert (handle.parent, handle.children, handle.gaussians) == ("object-0", ("subpart-2",), 2)
    np.testing.assert_allclose(handle.centroid, [0.35, 0, 0.65], atol=1e-6)
    np.testing.assert_allclose(handle.box_min, [0.3, 0, 0.6], atol=1e-6)
    np.testing.assert_allclose(handle.box_max, [0.4, 0, 0.7], atol=1e-6)
    np.testing.assert_allclose(
        handle.oriented_box.half_extents, [np.hypot(0.05, 0.05), 0, 0], atol=1e-6
    )
    mug = graph.node("object-0")
    assert (mug.parent, mug.children, mug.gaussians, mug.seen) == (
        None,
        ("part-0", "part-1"),
        6,
        True,
    )
    assert graph.node("subpart-2").seen is False  # never seen by a view
    assert graph.node("superpoint-0").children == () and not graph.node("superpoint-0").seen
    assert graph.neighbours == 5  # k = 10 of the default graph, capped at N − 1
    # six Gaussians, five neighbours each: every pair of different regions touches
    body, handle_part = graph.node("part-0"), graph.node("part-1")
    edges = {(e.a, e.b): e for e in graph.edges}
    assert edges[("part-0", "part-1")].contacts == body.gaussians * handle_part.gaussians
    assert edges[("part-0", "part-1")].shares == (1.0, 1.0)
    assert not any(e.level == 3 for e in graph.edges)  # one object touches nothing


def test_edges_match_the_per_pair_reference(small_field):
    from thgs.field import load_field
    from thgs.field_scene import open_field_scene
    from thgs.graph.knn import nearest_neighbors

    field, scene = open_field_scene(small_field)
    graph = scene_graph(field, scene.gaussians)
    means = scene.gaussians.means.numpy().astype(np.float64)
    _, index = nearest_neighbors(means, graph.neighbours + 1, 2.0)
    neighbors = np.where(
        (index < len(field)) & (index != np.arange(len(field))[:, None]), index, -1
    )
    for level in range(4):
        expected = _reference_edges(field.labels[:, level], neighbors, level)
        found = {(e.a, e.b): (e.contacts, *e.shares) for e in graph.edges if e.level == level}
        assert found.keys() == expected.keys()
        for key, (contacts, share_a, share_b) in expected.items():
            assert found[key][0] == contacts
            np.testing.assert_allclose(found[key][1:], (share_a, share_b))
    for node in graph.nodes:  # sizes, parents and children are the field's
        assert node.gaussians == int(field.sizes(node.level)[node.region])
        if node.level < 3:
            assert node.parent == node_id(node.level + 1, field.parent(node.level, node.region))
    assert load_field(small_field).region_counts == tuple(
        sum(node.level == k for node in graph.nodes) for k in range(4)
    )


def test_names_are_the_most_confident_phrases(small_field):
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.query import FieldQuery

    field, scene = open_field_scene(small_field)
    engine = FieldQuery(field, field_text_encoder(field, small_field))
    vocabulary = ("table", "mug", "teddy bear", "chair", "lamp", "giraffe")
    graph = scene_graph(field, scene.gaussians, engine=engine, vocabulary=vocabulary, names=2)
    confidence = engine.confidence(list(vocabulary), 3)
    for node in graph.nodes:
        if node.level == 0 or not node.seen:
            assert node.names == ()  # superpoints and unseen regions have no feature
            continue
        assert len(node.names) == 2
        if node.level != 3:
            continue
        best = int(np.argmax(confidence[:, node.region]))
        assert node.names[0].text == vocabulary[best] and len(node.names) == 2
        assert node.names[0].confidence == pytest.approx(confidence[best, node.region])
        assert node.names[0].confidence >= node.names[1].confidence
    with pytest.raises(InputError, match="needs the field's query engine"):
        scene_graph(field, scene.gaussians, vocabulary=vocabulary)


def test_the_file_follows_its_schema_and_reads_back(tmp_path):
    graph = scene_graph(mug_field(), _mug_gaussians(), field_name="mug.thgs")
    path = tmp_path / "graph.json"
    write_scene_graph(path, graph)
    document = json.loads(path.read_text())
    jsonschema.Draft202012Validator.check_schema(scene_graph_schema())
    jsonschema.validate(document, scene_graph_schema())
    assert read_scene_graph(path) == graph
    write_scene_graph(
        tmp_path / "again.json", scene_graph(mug_field(), _mug_gaussians(), field_name="mug.thgs")
    )
    assert (tmp_path / "again.json").read_bytes() == path.read_bytes()  # the same ids and bytes


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: {**d, "format": "other"}, "not a thgs scene graph"),
        (lambda d: {**d, "version": 2}, "written by a newer thgs (version 2), this one reads 1"),
        (lambda d: {**d, "nodes": [{**d["nodes"][0], "id": "room-1"}]}, "at nodes/0/id"),
        (lambda d: {**d, "edges": [{**d["edges"][0], "shares": [2, 0]}]}, "at edges/0/shares/0"),
        (lambda d: {k: v for k, v in d.items() if k != "nodes"}, "'nodes' is a required property"),
    ],
)
def test_a_file_that_is_not_a_scene_graph_is_named(tmp_path, change, message):
    graph = scene_graph(mug_field(), _mug_gaussians())
    path = tmp_path / "graph.json"
    path.write_text(json.dumps(change(graph.to_json())))
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        read_scene_graph(path)
    assert caught.value.source == str(path)


def test_a_graph_path_that_is_a_folder_is_refused(tmp_path):
    with pytest.raises(InputError, match="is a folder"):
        write_scene_graph(tmp_path, scene_graph(mug_field(), _mug_gaussians()))


def test_thgs_export_graph(small_field, tmp_path, capsys):
    words = tmp_path / "words.txt"
    words.write_text("table\nmug\nteddy bear\n")
    path = tmp_path / "graph.json"
    argv = ["export", str(small_field), "--graph", str(path), "--vocabulary", str(words)]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    graph = read_scene_graph(path)
    assert graph.vocabulary == ("table", "mug", "teddy bear")
    assert any(node.names and node.names[0].text == "mug" for node in graph.nodes)
    assert f"wrote{path}" in "".join(out.split())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph.json", "words.txt"]


def test_thgs_export_graph_bad_input(small_field, tmp_path, capsys):
    words = tmp_path / "words.txt"
    words.write_text("mug\n")
    code, _, err = run_cli(["export", str(small_field), "--graph", str(tmp_path)], capsys)
    assert code == 2 and "is a folder" in " ".join(err.split())
    argv = ["export", str(small_field), "-o", str(tmp_path / "x"), "--labels"]
    code, _, err = run_cli([*argv, "--vocabulary", str(words)], capsys)
    assert code == 2 and "--vocabulary" in err and "--graph" in err
    assert not (tmp_path / "x").exists()
    code, _, err = run_cli(["export", str(small_field), "--labels"], capsys)
    assert code == 2 and "--out" in err
    code, _, err = run_cli(["export", str(small_field)], capsys)
    assert code == 2 and "nothing to export" in err
