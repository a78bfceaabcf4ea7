"""PLY reader and writer: layout by hand, bit-exact round trips, the real sample, bad files."""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import plyfile
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from conftest import random_gaussians
from thgs import Gaussians, InputError, read_ply, write_ply


def raw_ply(path, columns: dict[str, np.ndarray], *, text: bool = False) -> None:
    """Write a PLY with exactly these vertex properties, independent of thgs."""
    n = len(next(iter(columns.values())))
    records = np.empty(n, dtype=[(name, values.dtype) for name, values in columns.items()])
    for name, values in columns.items():
        records[name] = values
    plyfile.PlyData([plyfile.PlyElement.describe(records, "vertex")], text=text).write(str(path))


def inria_columns(
    n: int, *, scales: int = 3, rest: int = 45, normals: bool = True, seed: int = 0
) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    names = (
        ["x", "y", "z"]
        + (["nx", "ny", "nz"] if normals else [])
        + [f"f_dc_{i}" for i in range(3)]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(scales)]
        + [f"rot_{i}" for i in range(4)]
    )
    return {name: rng.normal(size=n).astype(np.float32) for name in names}


def sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_layout_by_hand(tmp_path):
    """f_rest is channel-major: f_rest_0..14 are red coefficients 1..15, then green, then blue."""
    columns = inria_columns(5, rest=45)
    raw_ply(tmp_path / "a.ply", columns)
    g = read_ply(tmp_path / "a.ply")
    assert (len(g), g.kind, g.sh_degree) == (5, "3dgs", 3)
    assert g.sh.shape == (5, 16, 3)
    np.testing.assert_array_equal(g.sh[:, 0, 1].numpy(), columns["f_dc_1"])
    np.testing.assert_array_equal(g.sh[:, 1, 0].numpy(), columns["f_rest_0"])
    np.testing.assert_array_equal(g.sh[:, 15, 0].numpy(), columns["f_rest_14"])
    np.testing.assert_array_equal(g.sh[:, 1, 1].numpy(), columns["f_rest_15"])
    np.testing.assert_array_equal(g.sh[:, 4, 2].numpy(), columns["f_rest_33"])
    np.testing.assert_array_equal(g.quats[:, 0].numpy(), columns["rot_0"])  # w first
    np.testing.assert_array_equal(g.scales[:, 2].numpy(), columns["scale_2"])
    np.testing.assert_array_equal(g.normals[:, 1].numpy(), columns["ny"])
    np.testing.assert_array_equal(g.means[:, 2].numpy(), columns["z"])


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("sh_degree", [0, 3])
@pytest.mark.parametrize("normals", [True, False])
def test_round_trip_is_bit_exact(tmp_path, kind, sh_degree, normals):
    g = random_gaussians(257, kind=kind, sh_degree=sh_degree, normals=normals, seed=sh_degree)
    write_ply(tmp_path / "a.ply", g)
    back = read_ply(tmp_path / "a.ply")
    assert (back.kind, back.sh_degree, len(back)) == (kind, sh_degree, 257)
    assert (back.normals is None) == (not normals)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(back, name), getattr(g, name)), name
    write_ply(tmp_path / "b.ply", back)
    assert sha256(tmp_path / "a.ply") == sha256(tmp_path / "b.ply")


def test_trainer_layout_is_reproduced_byte_for_byte(tmp_path):
    """A file written like the INRIA trainers (plyfile, property order) comes back unchanged."""
    for scales, rest in ((3, 45), (2, 0), (2, 24)):
        raw_ply(tmp_path / "trainer.ply", inria_columns(100, scales=scales, rest=rest))
        write_ply(tmp_path / "ours.ply", read_ply(tmp_path / "trainer.ply"))
        assert sha256(tmp_path / "trainer.ply") == sha256(tmp_path / "ours.ply")


def test_extra_properties_are_carried(tmp_path):
    columns = inria_columns(7, rest=0)
    columns["semantic_id"] = np.arange(7, dtype=np.int32)
    raw_ply(tmp_path / "a.ply", columns)
    g = read_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(g.extras["semantic_id"], np.arange(7))
    write_ply(tmp_path / "b.ply", g)
    assert sha256(tmp_path / "a.ply") == sha256(tmp_path / "b.ply")


def test_ascii_ply_reads(tmp_path):
    columns = inria_columns(3, scales=2, rest=9)
    raw_ply(tmp_path / "a.ply", columns, text=True)
    g = read_ply(tmp_path / "a.ply")
    assert (g.kind, g.sh_degree) == ("2dgs", 1)
    np.testing.assert_allclose(g.opacities.numpy(), columns["opacity"], rtol=1e-6)


@settings(max_examples=25, deadline=None)
@given(
    values=hnp.arrays(
        np.float32, (3, 14), elements=st.floats(width=32, allow_nan=False, allow_infinity=False)
    ),
)
def test_round_trip_any_finite_float(tmp_path_factory, values):
    """Every finite float32, subnormals and −0.0 included, survives bit for bit (log-scales
    up to 44, below which exp(2 · scale) is finite in float32)."""
    values = values.copy()
    values[:, 3:7][(values[:, 3:7] == 0).all(axis=1)] = 1.0  # no zero quaternion
    values[:, 7:10] = np.minimum(values[:, 7:10], 44.0)  # a finite variance
    g = Gaussians(
        means=torch.from_numpy(values[:, 0:3].copy()),
        quats=torch.from_numpy(values[:, 3:7].copy()),
        scales=torch.from_numpy(values[:, 7:10].copy()),
        opacities=torch.from_numpy(values[:, 10].copy()),
        sh=torch.from_numpy(values[:, 11:14].copy()).reshape(3, 1, 3),
    )
    path = tmp_path_factory.mktemp("ply") / "a.ply"
    write_ply(path, g)
    back = read_ply(path)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert np.array_equal(
            getattr(back, name).numpy().view(np.int32), getattr(g, name).numpy().view(np.int32)
        ), name


def test_real_sample(shared_data, tmp_path):
    path = shared_data / "ply_3dgs_train1000.ply"
    g = read_ply(path)
    assert (len(g), g.kind, g.sh_degree) == (1000, "3dgs", 3)
    assert g.normals is not None and not g.extras
    # stored values as documented in SOURCES.md: logits, log-scales, unnormalised quaternions
    assert -5.3 < float(g.opacities.min()) < -5.0 and 3.2 < float(g.opacities.max()) < 3.4
    assert -7.5 < float(g.scales.min()) < -7.3 and -0.7 < float(g.scales.max()) < -0.5
    norms = g.quats.norm(dim=1)
    assert float(norms.min()) < 0.7 and float(norms.max()) > 1.0
    opacity = g.activated_opacities()
    assert float(opacity.min()) > 0 and float(opacity.max()) < 1
    torch.testing.assert_close(g.unit_quats().norm(dim=1), torch.ones(1000))
    write_ply(tmp_path / "copy.ply", g)
    assert sha256(tmp_path / "copy.ply") == sha256(path)


def test_bundled_sample_is_the_shared_one(shared_data):
    from conftest import REPO

    assert sha256(REPO / "examples/data/train-1000.ply") == sha256(
        shared_data / "ply_3dgs_train1000.ply"
    )


# --- bad input: one exception type, the file named, the problem said ---------------------------


def without(columns, *names):
    return {key: value for key, value in columns.items() if key not in names}


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: without(inria_columns(4), "opacity"), r"missing properties \['opacity'\]"),
        (lambda: without(inria_columns(4), "rot_3"), r"missing properties \['rot_3'\]"),
        (lambda: without(inria_columns(4), "scale_0", "scale_1", "scale_2"), "missing properties"),
        (lambda: inria_columns(4, scales=4), "4 scale properties"),
        (lambda: without(inria_columns(4), "scale_1"), "missing properties|not numbered"),
        (lambda: without(inria_columns(4), "f_rest_3"), "not numbered"),
        (lambda: inria_columns(4, rest=10), "10 f_rest_"),
        (lambda: without(inria_columns(4), "nz"), "partial normals"),
        (
            lambda: {**inria_columns(4), "x": np.array([0, np.nan, 0, 0], np.float32)},
            "means has NaN or infinite values in 1 Gaussians .first: Gaussian 1",
        ),
        (
            lambda: {**inria_columns(4), "scale_1": np.array([0, 0, np.inf, 0], np.float32)},
            "scales has NaN or infinite",
        ),
        (
            lambda: {
                **inria_columns(4),
                **{f"rot_{i}": np.array([1, 0, 1, 1], np.float32) for i in range(4)},
            },
            "zero quaternion, which is no rotation .first: Gaussian 1",
        ),
        (  # finite log-scales whose exp(2 · scale) is inf in float32
            lambda: {
                **inria_columns(4),
                "scale_2": np.array([0, 45, 0, 120], np.float32),
            },
            r": 2 Gaussians have log-scales above 44\.4 \(up to 120; first: Gaussian 1\), whose "
            r"variance exp\(2 · scale\) overflows torch\.float32; scales must be log standard "
            r"deviations$",
        ),
    ],
)
def test_bad_properties(tmp_path, make, message):
    path = tmp_path / "bad.ply"
    raw_ply(path, make())
    with pytest.raises(InputError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)


def test_cli_prints_the_offending_values_in_brackets(tmp_path, capsys):
    """The console's markup must not eat ``[nan, …]`` or ``[n, D]`` (it did: "value )")."""
    from thgs.cli import entrypoint
    from thgs.cli._console import error

    columns = inria_columns(4)
    columns["x"][1] = np.nan
    path = tmp_path / "nan.ply"
    raw_ply(path, columns)
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["info", str(path)])
    assert exit_info.value.code == 2
    value = [float(columns[name][1]) for name in ("x", "y", "z")]
    assert " ".join(capsys.readouterr().err.split()) == (
        f"error: {path}: means has NaN or infinite values in 1 Gaussians (first: Gaussian 1, "
        f"value {value})"
    )
    error("f.npy: expected an [n, D] array of floats, got [4]")
    assert capsys.readouterr().err == "error: f.npy: expected an [n, D] array of floats, got [4]\n"


def test_bad_files(tmp_path):
    good = tmp_path / "good.ply"
    raw_ply(good, inria_columns(50))
    data = good.read_bytes()
    cases = {
        "missing.ply": (None, "no such file"),
        "empty.ply": (b"", "empty"),
        "truncated.ply": (data[: len(data) - 100], "not a readable PLY"),
        "header_only.ply": (data[: data.index(b"end_header") + 11], "not a readable PLY"),
        "text.ply": (b"hello world\n", "not a readable PLY"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        with pytest.raises(InputError, match=message) as info:
            read_ply(path)
        assert str(info.value).startswith(f"{path}: ")


def test_invisible_scene_is_warned_about(tmp_path, caplog):
    """Every opacity below 1/255 (what the rasterizers skip): read, with a warning naming the
    file; one visible Gaussian is enough to stay quiet."""
    columns = inria_columns(6)
    columns["opacity"] = np.full(6, -8.0, np.float32)  # sigmoid(-8) = 3.4e-4
    path = tmp_path / "faint.ply"
    raw_ply(path, columns)
    with caplog.at_level(logging.WARNING, logger="thgs"):
        assert len(read_ply(path)) == 6
    assert caplog.messages == [
        f"{path}: all 6 Gaussians have an opacity below 1/255 (at most 0.000335), so nothing of "
        "the scene is visible; opacities must be logits (sigmoid gives the opacity)"
    ]
    caplog.clear()
    columns["opacity"][4] = -5.0  # sigmoid(-5) = 0.0067 > 1/255
    raw_ply(path, columns)
    with caplog.at_level(logging.WARNING, logger="thgs"):
        read_ply(path)
    assert caplog.messages == []


def test_no_vertex_element_and_no_rows(tmp_path):
    records = np.zeros(3, dtype=[("a", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(records, "face_data")]).write(
        str(tmp_path / "a.ply")
    )
    with pytest.raises(InputError, match="no 'vertex' element"):
        read_ply(tmp_path / "a.ply")
    raw_ply(tmp_path / "b.ply", {k: v[:0] for k, v in inria_columns(1).items()})
    with pytest.raises(InputError, match="no Gaussians"):
        read_ply(tmp_path / "b.ply")


def test_failed_write_leaves_nothing(tmp_path):
    g = random_gaussians(10)
    bad = Gaussians(g.means, torch.zeros(10, 4), g.scales, g.opacities, g.sh)
    with pytest.raises(InputError, match="zero quaternion"):
        write_ply(tmp_path / "out.ply", bad)
    assert list(tmp_path.iterdir()) == []
    write_ply(tmp_path / "out.ply", g)
    before = sha256(tmp_path / "out.ply")
    with pytest.raises(InputError):
        write_ply(tmp_path / "out.ply", bad)
    assert sha256(tmp_path / "out.ply") == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.ply"]
