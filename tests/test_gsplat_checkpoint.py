"""gsplat trainer checkpoints (``ckpts/ckpt_*.pt``) read into the same Gaussians as the PLY of
the same model: against gsplat's own PLY exporter, against a real 3DGS PLY, for 2DGS, for a
multi-GPU run, and their bad input."""

from __future__ import annotations

import logging
import math
import os

import pytest
import torch

from conftest import random_cameras, random_gaussians
from thgs import InputError, load_scene, read_ply, write_ply
from thgs.scene import SH_C0, read_gsplat_checkpoint, write_cameras_json


def splats_of(gaussians, *, third_scale=None):
    """The ``splats`` state dict gsplat's trainer would hold for these Gaussians."""
    scales = gaussians.scales
    if third_scale is not None:  # 2DGS: gsplat keeps a third, unused scale
        scales = torch.cat([scales, torch.full((len(gaussians), 1), third_scale)], dim=1)
    return {
        "means": gaussians.means.clone(),
        "quats": gaussians.quats.clone(),
        "scales": scales.clone(),
        "opacities": gaussians.opacities.clone(),
        "sh0": gaussians.sh[:, :1].clone(),
        "shN": gaussians.sh[:, 1:].clone(),
    }


def save(path, splats, step=29999):
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"step": step, "scene_id": 0, "splats": splats}, path)
    return path


def assert_same(a, b):
    for name in ("means", "quats", "scales", "opacities", "sh"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0)


def test_3dgs_checkpoint_equals_the_real_ply(tmp_path, shared_data):
    ply = read_ply(shared_data / "ply_3dgs_train1000.ply")
    path = save(tmp_path / "ckpts" / "ckpt_29999_rank0.pt", splats_of(ply))
    gaussians = read_gsplat_checkpoint(path)
    assert gaussians.kind == "3dgs" and gaussians.sh_degree == 3
    assert_same(gaussians, ply)
    assert gaussians.normals is None


def test_checkpoint_equals_gsplats_own_ply_export(tmp_path):
    exporter = pytest.importorskip("gsplat.exporter", reason="gsplat (the gpu extra) is missing")
    splats = splats_of(random_gaussians(300, kind="3dgs", sh_degree=2, seed=3))
    exporter.export_splats(**splats, format="ply", save_to=str(tmp_path / "export.ply"))
    path = save(tmp_path / "ckpts" / "ckpt_6999_rank0.pt", splats, step=6999)
    assert_same(read_gsplat_checkpoint(path), read_ply(tmp_path / "export.ply"))


def test_2dgs_checkpoint_drops_the_unused_scale(tmp_path):
    surfels = random_gaussians(200, kind="2dgs", sh_degree=3, normals=False, seed=1)
    write_ply(tmp_path / "point_cloud.ply", surfels)
    path = save(
        tmp_path / "result" / "ckpts" / "ckpt_29999.pt", splats_of(surfels, third_scale=-3.0)
    )
    gaussians = read_gsplat_checkpoint(path)
    assert gaussians.kind == "2dgs"
    assert_same(gaussians, read_ply(tmp_path / "point_cloud.ply"))
    # the same name beside simple_trainer's cfg.yml is a 3DGS checkpoint of an older gsplat
    (tmp_path / "result" / "cfg.yml").write_text("data_dir: data/garden\n")
    assert read_gsplat_checkpoint(path).kind == "3dgs"
    assert read_gsplat_checkpoint(path, kind="2dgs").kind == "2dgs"


def test_ranks_are_concatenated_in_order(tmp_path):
    whole = random_gaussians(90, sh_degree=1, normals=False, seed=2)
    for rank in range(3):
        part = whole.select(torch.arange(rank * 30, rank * 30 + 30))
        save(tmp_path / "ckpts" / f"ckpt_999_rank{rank}.pt", splats_of(part), step=999)
    assert_same(read_gsplat_checkpoint(tmp_path / "ckpts" / "ckpt_999_rank1.pt"), whole)


def test_appearance_optimised_checkpoint_keeps_base_colours(tmp_path):
    gaussians = random_gaussians(20, sh_degree=0, normals=False, seed=4)
    splats = splats_of(gaussians)
    del splats["sh0"], splats["shN"]
    rgb = torch.tensor([[0.2, 0.5, 0.9]]).repeat(20, 1)
    splats |= {"features": torch.zeros(20, 32), "colors": torch.logit(rgb)}
    read = read_gsplat_checkpoint(save(tmp_path / "ckpt_10_rank0.pt", splats))
    assert read.sh_degree == 0
    torch.testing.assert_close(read.dc_colors(), rgb)
    torch.testing.assert_close(read.sh[:, 0], (rgb - 0.5) / SH_C0)


def test_result_folder_is_a_scene(tmp_path):
    result = tmp_path / "results" / "garden"
    gaussians = random_gaussians(50, sh_degree=1, normals=False, seed=5)
    save(result / "ckpts" / "ckpt_6999_rank0.pt", splats_of(gaussians), step=6999)
    newest = random_gaussians(60, sh_degree=1, normals=False, seed=6)
    save(result / "ckpts" / "ckpt_29999_rank0.pt", splats_of(newest))
    write_cameras_json(tmp_path / "cameras.json", random_cameras(3, centred=True))
    scene = load_scene(result, source=tmp_path / "cameras.json")
    assert scene.ply_path == result / "ckpts" / "ckpt_29999_rank0.pt"
    assert_same(scene.gaussians, newest)
    assert len(scene.cameras) == 3
    assert scene.found[0] == f"gsplat result folder {result}, checkpoint ckpt_29999_rank0.pt"
    assert "read as 3DGS" in scene.found[1]
    assert_same(load_scene(result, iteration=6999).gaussians, gaussians)
    assert_same(load_scene(result / "ckpts" / "ckpt_6999_rank0.pt").gaussians, gaussians)
    with pytest.raises(
        InputError, match=r"no checkpoint of step 5; the folder has \[6999, 29999\]"
    ):
        load_scene(result, iteration=5)


def test_thgs_info_reads_a_result_folder(tmp_path, capsys):
    from thgs.cli import entrypoint

    result = tmp_path / "result"
    save(
        result / "ckpts" / "ckpt_29999.pt",
        splats_of(random_gaussians(40, kind="2dgs", seed=7), third_scale=0.0),
    )
    entrypoint(["info", str(result), "--json"])
    out = capsys.readouterr().out
    assert '"kind": "2dgs"' in out and '"count": 40' in out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"not a checkpoint", "not a readable PyTorch checkpoint"),
        ({"step": 1}, "a dict with 'splats'"),
        ({"splats": {"quats": torch.zeros(3, 4)}}, "'splats' has no 'means' tensor"),
        ("shape", r"splats\['quats'\] must be \[5, 4\], got \[5, 3\]"),
        ("sh", r"splats\['shN'\] must be \[N, K − 1, 3\]"),
        ("colour", "neither sh0/shN nor colors"),
        ("int", "has dtype torch.int64"),
        ("nan", "NaN or infinite"),
        ("huge", r"1 Gaussians have log-scales above 44\.4 \(up to 89; first: Gaussian 3\)"),
        ("empty", "holds no Gaussians"),
    ],
)
def test_bad_checkpoints(tmp_path, content, message):
    path = tmp_path / "ckpt_7_rank0.pt"
    splats = splats_of(random_gaussians(5, sh_degree=1, normals=False))
    if content == "shape":
        splats["quats"] = splats["quats"][:, :3]
    elif content == "sh":
        splats["shN"] = torch.zeros(5, 4, 3)
    elif content == "colour":
        del splats["sh0"], splats["shN"]
    elif content == "int":
        splats["means"] = splats["means"].long()
    elif content == "nan":
        splats["opacities"][2] = math.nan
    elif content == "huge":
        splats["scales"][3, 0] = 89.0  # exp(89) overflows float32
    elif content == "empty":
        splats = {key: value[:0] for key, value in splats.items()}
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content if isinstance(content, dict) else {"step": 7, "splats": splats}, path)
    with pytest.raises(InputError, match=message) as info:
        read_gsplat_checkpoint(path)
    assert str(info.value).startswith(str(path))


def test_invisible_checkpoint_is_warned_about(tmp_path, caplog):
    splats = splats_of(random_gaussians(5, sh_degree=1, normals=False))
    splats["opacities"] = torch.full((5,), -20.0)
    path = save(tmp_path / "ckpts" / "ckpt_7_rank0.pt", splats, step=7)
    with caplog.at_level(logging.WARNING, logger="thgs"):
        read_gsplat_checkpoint(path)
    assert caplog.messages == [
        f"{path}: all 5 Gaussians have an opacity below 1/255 (at most 2.06e-09), so nothing of "
        "the scene is visible; opacities must be logits (sigmoid gives the opacity)"
    ]


def test_a_checkpoint_name_gsplat_does_not_write_needs_the_kind(tmp_path):
    path = save(tmp_path / "model.pt", splats_of(random_gaussians(5, sh_degree=0)))
    with pytest.raises(InputError, match="cannot tell whether this checkpoint is 3DGS or 2DGS"):
        read_gsplat_checkpoint(path)
    assert read_gsplat_checkpoint(path, kind="3dgs").kind == "3dgs"
    with pytest.raises(InputError, match="ranks are \\[1\\]"):
        read_gsplat_checkpoint(save(tmp_path / "ckpt_3_rank1.pt", splats_of(random_gaussians(5))))
    (tmp_path / "empty" / "ckpts").mkdir(parents=True)
    with pytest.raises(InputError, match="not a gsplat result folder"):
        load_scene(tmp_path / "empty")


class _Hostile:
    """Unpickling this would run ``os.system``: what a checkpoint must never get to do."""

    def __reduce__(self):
        import os

        return (os.system, ("touch pwned",))


def test_a_checkpoint_holding_code_is_refused_without_torch_s_advice(tmp_path):
    path = tmp_path / "ckpt_7_rank0.pt"
    torch.save({"step": 7, "splats": {"means": _Hostile()}}, path)
    with pytest.raises(InputError) as info:
        read_gsplat_checkpoint(path)
    message = str(info.value)
    assert message.startswith(f"{path}: holds Python objects besides tensors (")
    assert "os.system" in message or "posix.system" in message
    assert "weights_only" not in message and "\x1b[" not in message
    assert not (tmp_path / "pwned").exists() and not os.path.exists("pwned")
