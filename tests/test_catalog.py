"""A vocabulary answered in one pass (thgs.catalog, ``thgs catalog``): the vocabulary file read
strictly, overlaps resolved by the stated rule (checked by hand and against a per-Gaussian
reference), the files written whole or not at all, and the command end to end."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

import numpy as np
import pytest

from conftest import run_cli
from test_field import mug_field
from thgs.catalog import CATALOG_FILES, catalog_field, read_vocabulary, write_catalog
from thgs.errors import InputError
from thgs.query import QueryConfig, Regions, Selection
from thgs.scene import read_ply

# --- the vocabulary file --------------------------------------------------------------------------


def test_a_vocabulary_is_its_lines_without_blanks_and_comments(tmp_path):
    path = tmp_path / "words.txt"
    path.write_text("\ufeff# objects\nmug\n\n  teddy bear  \n#parts\nmug handle\r\nTable\n")
    assert read_vocabulary(path) == ("mug", "teddy bear", "mug handle", "Table")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "holds no phrase"),
        (b"# only a comment\n\n   \n", "holds no phrase"),
        (b"mug\ntable\nmug\n", "line 3 repeats 'mug' of line 1; list it once"),
        (b"mug\n\xff\xfe\x00b", "is not UTF-8 text (byte 4)"),
        (b"mug\x00\n", "holds NUL bytes: not a text file"),
    ],
)
def test_a_bad_vocabulary_is_named(tmp_path, content, message):
    path = tmp_path / "words.txt"
    path.write_bytes(content)
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        read_vocabulary(path)
    assert caught.value.source == str(path)


def test_a_missing_vocabulary_or_a_folder_is_named(tmp_path):
    with pytest.raises(InputError, match="vocabulary file not found"):
        read_vocabulary(tmp_path / "nowhere.txt")
    with pytest.raises(InputError, match="is a folder"):
        read_vocabulary(tmp_path)


# --- the overlap rule -----------------------------------------------------------------------------


@dataclass
class Answers:
    """An engine that answers given selections (the catalog only needs these three members)."""

    regions: Regions
    answers: dict[str, Selection]
    config: QueryConfig = QueryConfig()

    def select(self, texts, config=None):
        return [self.answers[text] for text in texts]


def _selection(regions: Regions, text: str, chosen, confidences=None) -> Selection:
    gaussians = np.zeros(len(regions), dtype=bool)
    for level, region, _ in chosen:
        gaussians |= regions.labels[:, level] == region
    return Selection(text, tuple(chosen), gaussians, None, 0.9, confidences)


def test_overlaps_go_to_the_most_confident_then_the_smaller_region_then_the_first_phrase():
    """The mug of docs/field.md: Gaussians 0–3 the body (sub-parts rim 0–1, wall 2–3), 4–5 the
    handle; object 0 holds all six."""
    regions = Regions.from_field(mug_field())
    answers = {
        "mug": _selection(regions, "mug", [(3, 0, 0.7)], (0.8,)),
        "body": _selection(regions, "body", [(2, 0, 0.6)], (0.8,)),  # ties mug: smaller wins
        "rim": _selection(regions, "rim", [(1, 0, 0.5)], (0.95,)),  # most confident
        "lip": _selection(regions, "lip", [(1, 0, 0.9)], (0.95,)),  # ties rim in all: rim first
        "handle": _selection(regions, "handle", [(2, 1, 0.6)], (0.7,)),  # below the mug's 0.8
        "giraffe": Selection("giraffe", (), np.zeros(6, bool), "nothing relevant", 0.01, None),
    }
    catalog = catalog_field(Answers(regions, answers), list(answers))
    assert catalog.labels.tolist() == [2, 2, 1, 1, 0, 0]
    assert [entry.kept for entry in catalog.entries] == [2, 2, 2, 0, 0, 0]
    assert [entry.found for entry in catalog.entries] == [True] * 5 + [False]
    assert catalog.scored_by == "confidence"


def test_without_confidences_relevancies_order_every_claim():
    regions = Regions.from_field(mug_field())
    answers = {
        "mug": _selection(regions, "mug", [(3, 0, 0.7)]),
        "handle": _selection(regions, "handle", [(2, 1, 0.6)]),  # below the mug's 0.7
        "rim": _selection(regions, "rim", [(1, 0, 0.9)]),
    }
    catalog = catalog_field(Answers(regions, answers), list(answers))
    assert catalog.scored_by == "relevancy"
    assert catalog.labels.tolist() == [2, 2, 0, 0, 0, 0]


def test_the_same_phrase_twice_or_none_is_refused():
    regions = Regions.from_field(mug_field())
    engine = Answers(regions, {})
    with pytest.raises(InputError, match=r"phrases given twice: \['mug'\]"):
        catalog_field(engine, ["mug", "table", "mug"])
    with pytest.raises(InputError, match="give at least one phrase"):
        catalog_field(engine, [])


def _reference_labels(engine, catalog) -> np.ndarray:
    """Per Gaussian, by a plain loop: every claim as (score, −size, −phrase index), the largest
    wins; −1 when unclaimed."""
    labels = np.full(len(engine.regions), -1)
    for i in range(len(engine.regions)):
        claims = []
        for entry in catalog.entries:
            selection = entry.selection
            scores = selection.region_confidence or tuple(s for _, _, s in selection.regions)
            for (level, region, _), score in zip(selection.regions, scores):
                if engine.regions.labels[i, level] == region:
                    size = int(engine.regions.sizes(level)[region])
                    claims.append((score, -size, -entry.index))
        if claims:
            labels[i] = -max(claims)[2]
    return labels


@pytest.fixture(scope="module")
def engine(small_field):
    from thgs.field import load_field
    from thgs.field_scene import field_text_encoder
    from thgs.query import FieldQuery

    field = load_field(small_field)
    return FieldQuery(field, field_text_encoder(field, small_field))


VOCABULARY = ("table", "table leg", "mug", "mug handle", "teddy bear", "lamp", "giraffe")


def test_a_real_field_matches_the_per_gaussian_reference(engine):
    catalog = catalog_field(engine, VOCABULARY)
    assert catalog.scored_by == "confidence"
    np.testing.assert_array_equal(catalog.labels, _reference_labels(engine, catalog))
    found = {entry.phrase for entry in catalog.entries if entry.found}
    assert "giraffe" not in found and {"table", "mug"} <= found
    for entry in catalog.entries:  # what a phrase keeps is always inside what it selected
        assert entry.selection.gaussians[catalog.labels == entry.index].all()
        assert entry.kept == int((catalog.labels == entry.index).sum())


# --- the files ------------------------------------------------------------------------------------


def test_the_catalog_files(engine, small_dataset, tmp_path):
    from thgs.scene import load_scene

    gaussians = load_scene(small_dataset).gaussians
    catalog = catalog_field(engine, VOCABULARY)
    files = write_catalog(tmp_path / "out", catalog, gaussians, engine, field_name="f.thgs")
    found = [entry for entry in catalog.entries if entry.found]
    assert [p.name for p in files[:4]] == list(CATALOG_FILES)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in files)
    assert len(files) == 4 + len(found)

    labels = np.load(tmp_path / "out" / "labels.npy")
    assert labels.dtype == np.int32 and np.array_equal(labels, catalog.labels)
    ply = read_ply(tmp_path / "out" / "labels.ply")
    assert np.array_equal(ply.extras["label"], catalog.labels)
    assert np.array_equal(ply.means.numpy(), gaussians.means.numpy())  # the scene, in its order

    document = json.loads((tmp_path / "out" / "catalog.json").read_text())
    assert [row["text"] for row in document["phrases"]] == list(VOCABULARY)
    assert document["unlabelled"] == int((catalog.labels < 0).sum())
    for row, entry in zip(document["phrases"], catalog.entries):
        assert row["label"] == entry.index and row["kept"] == entry.kept
        if entry.found:
            part = read_ply(tmp_path / "out" / row["ply"])
            assert len(part) == row["gaussians"] == int(entry.selection.gaussians.sum())
        else:
            assert "ply" not in row and row["reason"]
    table = (tmp_path / "out" / "catalog.md").read_text()
    assert "| 6 | giraffe | no: nothing relevant" in table
    # a phrase with a bar stays one cell of the table
    piped = catalog_field(engine, ("mug | cup",))
    write_catalog(tmp_path / "piped", piped, gaussians, engine, field_name="f.thgs")
    row = (tmp_path / "piped" / "catalog.md").read_text().splitlines()[4]
    assert row.startswith("| 0 | mug \\| cup | ") and row.count(" | ") == 6


def test_each_phrase_found_is_pictured_in_the_view_that_shows_most_of_it(
    engine, small_dataset, tmp_path
):
    from PIL import Image

    from thgs.catalog import PICTURE_CHOICE_SCALE, PICTURE_VIEWS
    from thgs.scene import load_scene
    from thgs.views import highlighted, selection_masks

    scene = load_scene(small_dataset)
    catalog = catalog_field(engine, VOCABULARY)
    files = write_catalog(
        tmp_path / "out",
        catalog,
        scene.gaussians,
        engine,
        field_name="f.thgs",
        cameras=scene.cameras,
    )
    found = [entry for entry in catalog.entries if entry.found]
    document = json.loads((tmp_path / "out" / "catalog.json").read_text())
    pictured = [row for row in document["phrases"] if "picture" in row]
    assert len(files) == 4 + len(found) + len(pictured) and pictured
    candidates = np.unique(np.linspace(0, len(scene.cameras) - 1, PICTURE_VIEWS).round())
    for row in pictured:
        entry = catalog.entries[row["label"]]
        # the view is the candidate whose quarter-size render shows most of the selection
        # (counted by brute force, one view and one selection at a time)
        counts = []
        for index in candidates.astype(int):
            camera = scene.cameras.select([int(index)])
            small = camera.resized(
                [round(int(camera.widths[0]) * PICTURE_CHOICE_SCALE)],
                [round(int(camera.heights[0]) * PICTURE_CHOICE_SCALE)],
            )
            counts.append(selection_masks(scene.gaussians, small, entry.selection.gaussians).sum())
        assert scene.cameras.stems.index(row["view"]) == int(candidates[int(np.argmax(counts))])
        image = np.asarray(Image.open(tmp_path / "out" / row["picture"]))
        camera = scene.cameras.select([scene.cameras.stems.index(row["view"])])
        height, width = int(camera.heights[0]), int(camera.widths[0])
        assert image.shape == (height, 2 * width, 3)
        # the right half is tinted exactly where the selection's mask is
        mask = selection_masks(scene.gaussians, camera, entry.selection.gaussians)
        photo = image[:, :width].astype(float) / 255
        expected = np.round(highlighted(photo, mask) * 255)
        assert np.abs(image[:, width:] - expected).max() <= 1 and mask.any()


def test_a_catalog_that_cannot_be_written_leaves_nothing(
    engine, small_dataset, tmp_path, monkeypatch
):
    import thgs.catalog
    from thgs.scene import load_scene

    gaussians = load_scene(small_dataset).gaussians
    catalog = catalog_field(engine, VOCABULARY)
    calls = []

    def fail_on_the_second(*args):
        calls.append(args)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return thgs.export.write_selection_ply(*args)

    monkeypatch.setattr(thgs.catalog, "write_selection_ply", fail_on_the_second)
    with pytest.raises(OSError):
        write_catalog(tmp_path / "out", catalog, gaussians, engine, field_name="f.thgs")
    assert not (tmp_path / "out").exists()
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "mine.txt").write_text("x")
    calls.clear()
    with pytest.raises(OSError):
        write_catalog(tmp_path / "kept", catalog, gaussians, engine, field_name="f.thgs")
    assert [p.name for p in (tmp_path / "kept").iterdir()] == ["mine.txt"]


# --- the command ----------------------------------------------------------------------------------


def test_thgs_catalog(small_field, tmp_path, capsys):
    words = tmp_path / "words.txt"
    words.write_text("\n".join(VOCABULARY) + "\n")
    out = tmp_path / "catalog"
    code, stdout, err = run_cli(["catalog", str(small_field), str(words), "-o", str(out)], capsys)
    assert code == 0, err
    document = json.loads((out / "catalog.json").read_text())
    found = sum("ply" in row for row in document["phrases"])
    assert f"{found} of {len(VOCABULARY)} phrases found" in " ".join(stdout.split())
    assert (out / "labels.ply").is_file() and (out / "mug.ply").is_file()
    assert not list(out.glob("*.png"))  # pictures only when asked for
    pictured = tmp_path / "pictured"
    code, _, err = run_cli(
        ["catalog", str(small_field), str(words), "-o", str(pictured), "--pictures"], capsys
    )
    assert code == 0, err
    assert (pictured / "mug.png").is_file() and (pictured / "mug.ply").is_file()


def test_thgs_catalog_names_a_bad_vocabulary_before_opening_the_field(tmp_path, capsys):
    words = tmp_path / "words.txt"
    words.write_text("mug\nmug\n")
    out = tmp_path / "catalog"
    missing_field = tmp_path / "none.thgs"
    code, _, err = run_cli(["catalog", str(missing_field), str(words), "-o", str(out)], capsys)
    assert code == 2 and "line 2 repeats 'mug' of line 1" in " ".join(err.split())
    assert not out.exists()
    (tmp_path / "file").write_text("x")
    code, _, err = run_cli(
        ["catalog", str(missing_field), str(words), "-o", str(tmp_path / "file")], capsys
    )
    assert code == 2 and "file" in err
