"""3D-OVS segmentation folders: layout, round trip, the query substitution, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from thgs import InputError
from thgs.eval import (
    SegmentationSet,
    query_text,
    read_3dovs_segmentations,
    write_3dovs_segmentations,
)


def example() -> SegmentationSet:
    rng = np.random.default_rng(0)
    wall = np.zeros((6, 8), dtype=bool)
    wall[:3] = True
    return SegmentationSet(
        classes=("wood wall", "red apple", "Pikachu"),
        views={
            "00": {"wood wall": wall, "red apple": ~wall, "Pikachu": np.zeros((6, 8), bool)},
            "03": {"red apple": rng.random((4, 5)) < 0.5},  # another size, one class only
        },
    )


def assert_same(a: SegmentationSet, b: SegmentationSet) -> None:
    assert a.classes == b.classes
    assert list(a.views) == list(b.views)
    for view in a.views:
        assert list(a.views[view]) == list(b.views[view])
        for name, mask in a.views[view].items():
            assert b.views[view][name].dtype == np.bool_
            np.testing.assert_array_equal(b.views[view][name], mask)


def test_round_trip_and_layout(tmp_path):
    folder = tmp_path / "scene" / "segmentations"
    segmentations = example()
    write_3dovs_segmentations(folder, segmentations)
    assert (folder / "classes.txt").read_text() == "wood wall\nred apple\nPikachu\n"
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*.png")) == [
        "00/Pikachu.png",
        "00/red apple.png",
        "00/wood wall.png",
        "03/red apple.png",
    ]
    with Image.open(folder / "00" / "wood wall.png") as image:
        assert (image.mode, image.size) == ("L", (8, 6))
        pixels = np.asarray(image)
    assert pixels[:3].tolist() == [[255] * 8] * 3 and pixels[3:].tolist() == [[0] * 8] * 3
    # what 3D-OVS's loader computes: (convert('L') / 255).astype(int8)
    with Image.open(folder / "03" / "red apple.png") as image:
        reference = (np.array(image.convert("L")) / 255.0).astype(np.int8)
    np.testing.assert_array_equal(reference, segmentations.views["03"]["red apple"])
    assert_same(read_3dovs_segmentations(folder), segmentations)
    assert_same(read_3dovs_segmentations(folder.parent), segmentations)  # the scene folder
    assert [p.name for p in folder.parent.iterdir()] == ["segmentations"]  # no temporary left


def test_bytes_are_deterministic(tmp_path):
    write_3dovs_segmentations(tmp_path / "a", example())
    write_3dovs_segmentations(tmp_path / "b", example())
    files = sorted(
        p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()
    )
    assert len(files) == 5
    for name in files:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_other_binary_png_modes_and_stray_files(tmp_path):
    folder = tmp_path / "segmentations"
    (folder / "07").mkdir(parents=True)
    (folder / "classes.txt").write_text("table\r\n\r\nchair\r\n")  # CRLF and a blank line
    mask = np.zeros((3, 4), dtype=bool)
    mask[1, 2] = True
    Image.fromarray(mask).save(folder / "07" / "table.png")  # mode "1"
    rgb = np.repeat((mask * 255).astype(np.uint8)[:, :, None], 3, axis=2)
    Image.fromarray(rgb).save(folder / "07" / "chair.png")  # grey RGB
    (folder / "07" / "notes.txt").write_text("not a mask")
    (folder / "07" / ".DS_Store").write_bytes(b"\0")
    (folder / "README").write_text("a stray file next to the views")
    read = read_3dovs_segmentations(folder)
    assert read.classes == ("table", "chair")
    assert list(read.views) == ["07"] and list(read.views["07"]) == ["table", "chair"]
    np.testing.assert_array_equal(read.views["07"]["table"], mask)
    np.testing.assert_array_equal(read.views["07"]["chair"], mask)


def test_query_text():
    assert query_text("wood wall") == "wood"
    assert query_text("wood") == "wood"
    assert query_text("Wood wall") == "Wood wall"  # exact match only, as in the protocol
    assert query_text("red apple") == "red apple"


def write_view(folder, classes, masks):
    (folder).mkdir(parents=True, exist_ok=True)
    if classes is not None:
        (folder / "classes.txt").write_text("".join(f"{c}\n" for c in classes))
    for relative, values in masks.items():
        (folder / relative).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.asarray(values, dtype=np.uint8)).save(folder / relative)


@pytest.mark.parametrize(
    ("classes", "masks", "culprit", "message"),
    [
        (None, {"00/a.png": [[0, 255]]}, "classes.txt", "no such file"),
        ([], {"00/a.png": [[0, 255]]}, "classes.txt", "lists no class"),
        (["a", "a"], {}, "classes.txt", "more than once"),
        (["a"], {"00/b.png": [[0, 255]]}, "00/b.png", "class 'b' is not in"),
        (
            ["a", "b"],
            {"00/a.png": [[0, 255]], "00/b.png": [[0, 255], [0, 0]]},
            "00/b.png",
            "mask is 2×2 but a.png in the same view is 2×1",
        ),
        (["a"], {"00/a.png": [[0, 128]]}, "00/a.png", r"not a binary mask: grey values \[0, 128\]"),
        (["a"], {"00/a.png": [[0, 1]]}, "00/a.png", "not a binary mask"),
    ],
)
def test_bad_folders(tmp_path, classes, masks, culprit, message):
    folder = tmp_path / "segmentations"
    write_view(folder, classes, masks)
    with pytest.raises(InputError, match=message) as info:
        read_3dovs_segmentations(folder)
    assert info.value.source == str(folder / culprit)


def test_unreadable_png_and_missing_folder(tmp_path):
    folder = tmp_path / "segmentations"
    write_view(folder, ["a"], {})
    (folder / "00").mkdir()
    (folder / "00" / "a.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="not a readable image") as info:
        read_3dovs_segmentations(folder)
    assert info.value.source == str(folder / "00" / "a.png")
    with pytest.raises(InputError, match="segmentations folder not found"):
        read_3dovs_segmentations(tmp_path / "nowhere")


def test_refuses_to_overwrite(tmp_path):
    folder = tmp_path / "segmentations"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not an empty folder; refusing to overwrite") as info:
        write_3dovs_segmentations(folder, example())
    assert info.value.source == str(folder)
    assert [p.name for p in folder.iterdir()] == ["keep.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["segmentations"]
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_3dovs_segmentations(a_file, example())
    empty = tmp_path / "empty"
    empty.mkdir()
    write_3dovs_segmentations(empty, example())  # an empty folder is replaced
    assert_same(read_3dovs_segmentations(empty), example())


@pytest.mark.parametrize(
    ("segmentations", "message"),
    [
        (SegmentationSet(("a", "a"), {}), "not unique"),
        (SegmentationSet(("a/b",), {}), "class name 'a/b' is not usable"),
        (SegmentationSet(("a",), {"..": {}}), "view name '..' is not usable"),
        (SegmentationSet((" a",), {}), "is not usable"),
        (SegmentationSet(("a",), {"00": {"b": np.zeros((2, 2), bool)}}), "'b' not in classes"),
        (SegmentationSet(("a",), {"00": {"a": np.zeros((2, 2), np.uint8)}}), "bool mask"),
        (
            SegmentationSet(
                ("a", "b"), {"0": {"a": np.zeros((2, 2), bool), "b": np.zeros((2, 3), bool)}}
            ),
            "different sizes",
        ),
    ],
)
def test_bad_sets_are_not_written(tmp_path, segmentations, message):
    with pytest.raises(InputError, match=message):
        write_3dovs_segmentations(tmp_path / "segmentations", segmentations)
    assert list(tmp_path.iterdir()) == []
