"""The view that shows a selection (thgs.views.best_views): a hand-built occlusion where the
answer is known, counts against per-view masks, and the query and demo pictures drawn there."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from conftest import look_at, run_cli
from thgs.errors import InputError
from thgs.scene import Cameras, Gaussians
from thgs.views import best_views, selection_masks, visible_pixels


def _blob(centre, count: int, spread: float, scale: float, seed: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    means = torch.tensor(centre, dtype=torch.float32) + spread * torch.randn(
        count, 3, generator=generator
    )
    return {
        "means": means,
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1),
        "scales": torch.full((count, 3), float(np.log(scale))),
        "opacities": torch.full((count,), 6.0),  # sigmoid ≈ 0.998: opaque
        "sh": torch.zeros(count, 1, 3),
    }


def _wall_and_ball():
    """A wide opaque wall at x = +1 in front of a small ball at x = −1: a camera at x = +6 sees
    the wall hide the ball, one at x = −6 sees the ball, one at y = +6 sees both side by side."""
    wall = _blob((1.0, 0.0, 0.0), 400, 0.0, 0.15, 0)
    ys, zs = torch.meshgrid(
        torch.linspace(-1.5, 1.5, 20), torch.linspace(-1.5, 1.5, 20), indexing="ij"
    )
    wall["means"] = torch.stack([torch.full((400,), 1.0), ys.reshape(-1), zs.reshape(-1)], dim=-1)
    ball = _blob((-1.0, 0.0, 0.0), 60, 0.15, 0.08, 1)
    gaussians = Gaussians(**{key: torch.cat([wall[key], ball[key]]) for key in wall}).check()
    eyes = [np.array([6.0, 0, 0]), np.array([-6.0, 0, 0]), np.array([0, 6.0, 0])]
    cameras = Cameras(
        viewmats=torch.tensor(np.stack([look_at(eye, np.zeros(3)) for eye in eyes])),
        Ks=torch.tensor([[[120.0, 0, 64], [0, 120.0, 48], [0, 0, 1]]] * 3, dtype=torch.float64),
        widths=torch.tensor([128] * 3),
        heights=torch.tensor([96] * 3),
        names=("front.png", "back.png", "side.png"),
    ).check()
    ball_selected = np.zeros(len(gaussians), dtype=bool)
    ball_selected[400:] = True
    return gaussians, cameras, ball_selected


def test_a_hidden_selection_is_drawn_where_it_shows():
    gaussians, cameras, ball = _wall_and_ball()
    wall = ~ball
    counts = visible_pixels(gaussians, cameras, np.stack([ball, wall], axis=1))
    assert counts[0, 0] == 0  # from the front the wall hides the ball
    assert counts[1, 0] > 0 and counts[2, 0] > 0
    assert counts[1, 0] > counts[2, 0] * 0.5  # the back sees all of it, the side part of it
    for view in range(3):  # the counts are the masks' pixels
        masks = selection_masks(gaussians, cameras.select([view]), np.stack([ball, wall], axis=1))
        assert counts[view].tolist() == masks.reshape(-1, 2).sum(axis=0).tolist()
    best = best_views(gaussians, cameras, np.stack([ball, wall, np.zeros_like(ball)], axis=1))
    assert best[0] == int(np.argmax(counts[:, 0])) and best[0] != 0
    assert best[1] == 0  # the wall faces the front camera
    assert best[2] == -1  # nothing selected: no view
    assert int(best_views(gaussians, cameras, ball)) == best[0]  # one [N] selection


def test_no_view_is_an_error():
    gaussians, cameras, ball = _wall_and_ball()
    with pytest.raises(InputError, match="no view to look in"):
        visible_pixels(gaussians, cameras.select([]), ball)


def test_thgs_query_draws_each_query_in_its_best_view(small_field, tmp_path, capsys):
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.query import FieldQuery

    out = tmp_path / "q"
    argv = [
        "query",
        str(small_field),
        "table",
        "mug",
        "a giraffe",
        "--views",
        "best",
        "-o",
        str(out),
    ]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    document = json.loads((out / "results.json").read_text())
    field, scene = open_field_scene(small_field)
    engine = FieldQuery(field, field_text_encoder(field, small_field))
    for entry in document["queries"]:
        selected = engine.select([entry["text"]])[0].gaussians
        if not selected.any():
            assert entry["view"] is None and entry["files"] == []
            continue
        counts = visible_pixels(scene.gaussians, scene.cameras, selected)
        assert entry["view"] == scene.cameras.stems[int(np.argmax(counts))]
        assert [p.rsplit("/", 1)[-1] for p in entry["files"]] == [f"{entry['view']}.png"]
