"""OpenHype's ScanNet++ benchmark: the annotation reader against a transcription of the
evaluator's ``_get_gt_data`` and every refusal; the localization rule by hand; the protocol on a
wall that covers every view (each prediction known pixel for pixel, so IoUs are computed by
hand); a synthetic dataset laid out as ``scannetpp_preprocess.py`` leaves a scene, scored with
the ground-truth selection; ``thgs suite`` finding that layout."""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from thgs import load_cameras, load_scene
from thgs.errors import InputError
from thgs.eval import (
    OpenHypeFrame,
    OpenHypeObject,
    evaluate_dataset,
    evaluate_openhype,
    find_ground_truth,
    openhype_localized,
    read_openhype_annotations,
    write_openhype_annotations,
)
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.openhype import openhype_views, part_prompt, read_openhype_frame
from thgs.eval.rules import langsplat_localized
from thgs.scene import Cameras, Gaussians
from thgs.scene.transforms_json import OPENGL_TO_OPENCV
from thgs.suite import SceneResult, SuiteReport, find_suite
from thgs.synthetic import write_openhype_scannetpp
from thgs.views import selection_opacity

SCENE = "5ee7c22ba0"


class Oracle:
    """A stand-in query engine: each prompt selects the Gaussians its table gives (none for a
    prompt it lacks); ``using`` gives the engine of another mode (``paper``: its own table)."""

    def __init__(self, table: dict[str, np.ndarray], n: int, mode="oracle", paper=None):
        self.table, self.n, self.paper = table, n, paper
        self.config = SimpleNamespace(mode=mode)
        self.regions = SimpleNamespace(space="oracle")
        self.asked: list[list[str]] = []

    def selected(self, texts):
        self.asked.append(list(texts))
        empty = np.zeros(self.n, dtype=bool)
        return np.stack([self.table.get(text, empty) for text in texts], axis=1)

    def using(self, **changes):
        assert changes == {"mode": "paper", "levels": None}
        return Oracle(self.paper if self.paper is not None else self.table, self.n, "paper")


# ------------------------------------------------------------------ the reference's reading


def reference_reading(folder: Path) -> list[dict]:
    """OpenHype's ``_get_gt_data``, transcribed: per sorted ``*.json`` the first mask
    (``convert("L") // 255``) and ``is_part`` of each category, every box appended."""
    frames = []
    for path in sorted(folder.glob("*.json")):
        document = json.loads(path.read_text())
        annotations: dict[str, dict] = {"camera_data": document["info"]}
        for entry in document["objects"]:
            label = entry["category"]
            box = np.asarray(entry["bbox"]).reshape(-1)
            if label not in annotations:
                annotations[label] = {"is_part": entry["is_part"]}
                grey = np.array(Image.open(folder / entry["path_to_mask"]).convert("L"))
                annotations[label]["mask"] = grey // 255
            if "bboxes" in annotations[label]:
                old = annotations[label]["bboxes"].reshape(-1, 4)
                annotations[label]["bboxes"] = np.concatenate([old, box.reshape(-1, 4)])
            else:
                annotations[label]["bboxes"] = box
        frames.append(annotations)
    return frames


def reference_iou(predicted: np.ndarray, truth: np.ndarray) -> float:
    """The evaluator's IoU: ``logical_and`` / ``logical_or`` sums of two 0/1 masks."""
    return np.sum(np.logical_and(truth, predicted)) / np.sum(np.logical_or(truth, predicted))


# ------------------------------------------------------------------ hand-made annotations


def rectangle(height, width, rows, cols) -> np.ndarray:
    mask = np.zeros((height, width), dtype=bool)
    mask[rows[0] : rows[1], cols[0] : cols[1]] = True
    return mask


def camtoworld(dx: float = 0.0, dy: float = 0.0) -> np.ndarray:
    """A camera at (dx, dy, 0) looking down +z (OpenCV), as nerfstudio's OpenGL camera→world."""
    pose = np.eye(4)
    pose[:2, 3] = dx, dy
    return pose @ OPENGL_TO_OPENCV


def frame(stem, objects, *, size=(20, 12), dx=0.0, dy=0.0, name=None) -> OpenHypeFrame:
    width, height = size
    focal = 20.0 * width / 20
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return OpenHypeFrame(
        stem, name or f"{stem}.JPG", width, height, K, camtoworld(dx, dy), "PINHOLE", tuple(objects)
    )


def obj(category, mask, boxes, is_part=False, path=None) -> OpenHypeObject:
    return OpenHypeObject(
        category, is_part, mask, np.asarray(boxes, dtype=np.float64).reshape(-1, 4), path
    )


@pytest.fixture
def written(tmp_path) -> Path:
    """Two frames: a chair and a leg of it; a repeated category with a second box."""
    chair = rectangle(12, 20, (0, 6), (0, 10))
    leg = rectangle(12, 20, (6, 12), (0, 4))
    other = rectangle(12, 20, (0, 12), (10, 20))
    frames = [
        frame(
            "DSC00002",
            [
                obj("chair", chair, [0, 0, 9, 5], path="masks/a/chair.png"),
                obj("leg of a chair", leg, [[0, 6, 3, 11]], True, "masks/a/leg.png"),
                obj("chair", other, [10, 0, 19, 11], path="masks/a/chair2.png"),
            ],
        ),
        frame("DSC00001", [obj("table", other, [10, 0, 19, 11], path="DSC00001_table.png")]),
    ]
    folder = tmp_path / "gt"
    write_openhype_annotations(folder, frames)
    return folder


def test_written_annotations_read_back_as_the_evaluator_reads_them(written, caplog):
    with caplog.at_level(logging.WARNING):
        frames = read_openhype_annotations(written)
    assert [f.stem for f in frames] == ["DSC00001", "DSC00002"]  # sorted, as glob + sorted
    assert "categories ['chair'] are annotated more than once" in caplog.text
    first, second = frames
    assert (first.image_name, first.view, first.width, first.height) == (
        "DSC00001.JPG",
        "DSC00001",
        20,
        12,
    )
    np.testing.assert_array_equal(first.camtoworld, camtoworld())
    np.testing.assert_array_equal(first.K, [[20, 0, 10], [0, 20, 6], [0, 0, 1]])
    assert [o.category for o in second.objects] == ["chair", "leg of a chair", "chair"]
    assert [(p.category, p.is_part) for p in second.prompts()] == [
        ("chair", False),
        ("leg of a chair", True),
    ]
    reference = reference_reading(written)
    for ours, theirs in zip(frames, reference):
        assert [p.category for p in ours.prompts()] == [k for k in theirs if k != "camera_data"]
        assert theirs["camera_data"]["name"] == ours.image_name
        for prompt in ours.prompts():
            entry = theirs[prompt.category]
            np.testing.assert_array_equal(prompt.mask, entry["mask"] == 1)
            np.testing.assert_array_equal(prompt.boxes, entry["bboxes"].reshape(-1, 4))
            assert prompt.is_part == entry["is_part"]
    # the repeated chair: the first mask, both boxes
    chair = second.prompts()[0]
    assert chair.mask.sum() == 60 and chair.boxes.tolist() == [[0, 0, 9, 5], [10, 0, 19, 11]]
    # writing what was read gives the same files
    again = written.parent / "again"
    write_openhype_annotations(again, frames)
    for path in sorted(p for p in written.rglob("*") if p.is_file()):
        assert (again / path.relative_to(written)).read_bytes() == path.read_bytes(), path


def test_only_grey_255_is_the_object(written):
    path = written / "masks" / "a" / "chair.png"
    grey = np.zeros((12, 20), dtype=np.uint8)
    grey[0, :3] = (255, 254, 1)
    Image.fromarray(grey).save(path)
    chair = read_openhype_frame(written / "DSC00002.json").prompts()[0]
    assert np.argwhere(chair.mask).tolist() == [[0, 0]]
    # white in colour or a 1-bit PNG are 255 after convert("L")
    Image.fromarray(np.stack([grey] * 3, axis=-1)).save(path)
    assert read_openhype_frame(written / "DSC00002.json").prompts()[0].mask.sum() == 1
    Image.fromarray(grey == 255).save(path)
    assert read_openhype_frame(written / "DSC00002.json").prompts()[0].mask.sum() == 1


def _edit(key_path, value):
    """A change of the second frame's JSON: set (or with ``...`` delete) a nested key."""

    def change(document):
        target = document
        for key in key_path[:-1]:
            target = target[key]
        if value is ...:
            del target[key_path[-1]]
        else:
            target[key_path[-1]] = value
        return document

    return change


BROKEN_JSON = [
    (lambda d: [d], "expected an object with 'info' and 'objects'"),
    (_edit(["info"], ...), "expected an object with 'info' and 'objects'"),
    (_edit(["info", "width"], ...), "info has no 'width'"),
    (_edit(["info", "height"], 0), "info: size 20×0 is not positive integers"),
    (_edit(["info", "width"], 20.5), "info: size 20.5×12 is not positive integers"),
    (_edit(["info", "name"], ...), "info has no 'name' string"),
    (_edit(["info", "fl_y"], ...), "info has no 'fl_y'"),
    (_edit(["info", "cx"], "10"), "info: 'cx' is '10', not a number"),
    (_edit(["info", "fl_x"], -1.0), "focal lengths fl_x -1, fl_y 20 must be positive"),
    (_edit(["info", "camera_model"], ...), "info has no 'camera_model' string"),
    (_edit(["info", "camera_model"], "OPENCV_FISHEYE"), "is not a perspective model"),
    (_edit(["info", "transform_matrix"], ...), "info has no 'transform_matrix'"),
    (_edit(["info", "transform_matrix"], np.eye(4)[:3].tolist()), "has shape [3, 4]"),
    (_edit(["info", "transform_matrix", 0, 0], float("nan")), "has NaN or infinite values"),
    (_edit(["objects"], ...), "no 'objects' list"),
    (_edit(["objects"], {"a": 1}), "no 'objects' list"),
    (_edit(["objects", 0, "category"], ...), "object 0 has no 'category' string"),
    (_edit(["objects", 0, "category"], " "), "object 0: 'category' is empty"),
    (_edit(["objects", 0, "category"], "camera_data"), "keeps the frame's camera"),
    (_edit(["objects", 1, "is_part"], ...), "object 1 ('leg of a chair') has no 'is_part'"),
    (_edit(["objects", 1, "is_part"], "yes"), "'is_part' is 'yes'; expected true or false"),
    (_edit(["objects", 0, "bbox"], ...), "object 0 ('chair') has no 'bbox'"),
    (_edit(["objects", 0, "bbox"], [1, 2, 3]), "'bbox' holds 3 numbers"),
    (_edit(["objects", 0, "bbox"], [1, 2, 3, "x"]), "'bbox' is not numbers"),
    (_edit(["objects", 0, "bbox"], [1, 2, 3, True]), "'bbox' is not numbers"),
    (_edit(["objects", 0, "bbox"], [1, 2, 3, float("inf")]), "'bbox' has NaN or infinite"),
    (_edit(["objects", 0, "path_to_mask"], ...), "object 0 ('chair') has no 'path_to_mask'"),
    (_edit(["objects", 0, "path_to_mask"], 3), "'path_to_mask' is not a path string"),
    (_edit(["objects", 0, "path_to_mask"], "masks/none.png"), "masks/none.png does not exist"),
]


@pytest.mark.parametrize(("change", "message"), BROKEN_JSON)
def test_malformed_annotations_are_refused_naming_the_file(written, change, message):
    path = written / "DSC00002.json"
    path.write_text(json.dumps(change(json.loads(path.read_text()))))
    with pytest.raises(InputError) as caught:
        read_openhype_annotations(written)
    assert str(caught.value).startswith(f"{path}: ") and message in str(caught.value)


def test_broken_masks_and_folders_are_refused(written, tmp_path):
    mask = written / "masks" / "a" / "leg.png"
    mask.write_bytes(b"not a png")
    with pytest.raises(InputError, match=f"^{mask}: not a readable image"):
        read_openhype_annotations(written)
    Image.fromarray(np.full((24, 40), 255, dtype=np.uint8)).save(mask)
    with pytest.raises(InputError) as caught:
        read_openhype_annotations(written)
    assert str(caught.value) == f"{mask}: mask is 40×24 but DSC00002.json's info says 20×12"
    Image.fromarray(rectangle(12, 20, (0, 2), (0, 2)).astype(np.uint8)).save(mask)  # a 0/1 mask
    with pytest.raises(InputError) as caught:
        read_openhype_annotations(written)
    assert str(caught.value) == (
        f"{mask}: mask has no pixel of grey 255 (values [0, 1]); OpenHype reads only 255 as the "
        "object (`// 255`), so it would score an empty mask"
    )
    (written / "DSC00002.json").write_text("{")
    with pytest.raises(InputError, match=r"DSC00002\.json: not valid JSON"):
        read_openhype_annotations(written)
    with pytest.raises(InputError, match="OpenHype annotation folder not found"):
        read_openhype_annotations(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no OpenHype annotation files"):
        read_openhype_annotations(tmp_path / "empty")


def test_nothing_is_written_over_an_existing_folder_or_from_bad_frames(written, tmp_path):
    frames = read_openhype_annotations(written)
    with pytest.raises(InputError, match="already exists and is not an empty folder"):
        write_openhype_annotations(written, frames)
    bad = [frames[0], frame("DSC00001", [])]
    with pytest.raises(InputError, match="two frames share a file name"):
        write_openhype_annotations(tmp_path / "x", bad)
    escaping = [
        frame("a", [obj("c", rectangle(12, 20, (0, 1), (0, 1)), [0, 0, 0, 0], False, "../c.png")])
    ]
    with pytest.raises(InputError, match=r"must be a relative \.png path inside the folder"):
        write_openhype_annotations(tmp_path / "x", escaping)
    empty = [frame("a", [obj("c", np.zeros((12, 20), bool), [0, 0, 0, 0], False, "c.png")])]
    with pytest.raises(InputError, match="empty mask"):
        write_openhype_annotations(tmp_path / "x", empty)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("part", "whole", "prompt"),
    [
        ("mug handle", "mug", "handle of a mug"),
        ("light bulb", "lamp", "light bulb of a lamp"),
        ("bear head", "teddy bear", "head of a teddy bear"),
        ("teddy bear arm", "teddy bear", "arm of a teddy bear"),
        ("book", "stack of books", "book of a stack of books"),
        ("Table Legs", "table", "Legs of a table"),
        ("lamp", "lamp shade", "lamp of a lamp shade"),  # nothing would remain: kept whole
    ],
)
def test_part_prompts_take_openhypes_form(part, whole, prompt):
    assert part_prompt(part, whole) == prompt


# ------------------------------------------------------------------ the localization rule


def test_localization_smooths_the_mixed_map_as_the_evaluator_does():
    """A mask of columns 0–39 in a 40×80 image. box_filter(M) is 1 up to column 25 (its window
    reaches 14 columns right; the left border mirrors the mask), so the mixed map is 1 there;
    box_filter of the mixed map is 1 (its peak) up to column 11 only. LangSplat's rule, on the
    unmixed map, would reach column 25."""
    mask = np.zeros((40, 80), dtype=bool)
    mask[:, :40] = True
    assert openhype_localized(mask, [(5, 0, 8, 39)])
    assert openhype_localized(mask, [(11, 20, 11, 20)])
    assert not openhype_localized(mask, [(12, 0, 20, 39)])
    assert langsplat_localized(mask[None].astype(float), [(12, 0, 20, 39)])
    assert openhype_localized(mask, [(50, 0, 60, 39), (8, 5, 3, 1)])  # corners in any order
    assert not openhype_localized(np.zeros((40, 80), dtype=bool), [(0, 0, 79, 39)])
    with pytest.raises(InputError, match=r"openhype_localized: expected an \[H, W\] mask"):
        openhype_localized(np.zeros(5, bool), [(0, 0, 1, 1)])
    with pytest.raises(InputError, match="openhype_localized: expected a bool or integer mask"):
        openhype_localized(np.zeros((4, 4)), [(0, 0, 1, 1)])
    with pytest.raises(InputError, match="openhype_localized: boxes must be one or more"):
        openhype_localized(mask, [])


# ------------------------------------------------------------------ the protocol by hand


def wall_scene(stems: list[str], offsets=(0.0,)) -> tuple[Gaussians, Cameras]:
    """A wall of opaque camera-facing surfels at depth 5, x, y in [−4, 4]: every pixel of the
    20×12 cameras (focal 20, looking down +z from (dx, |dx|, 0)) is covered, so a selection of
    the whole wall predicts every pixel and an empty one none."""
    steps = np.arange(-4.0, 4.01, 0.25)
    means = [[x, y, 5.0] for y in steps for x in steps]
    n = len(means)
    gaussians = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        scales=torch.full((n, 2), math.log(0.2)),
        opacities=torch.full((n,), math.log(0.99 / 0.01)),
        sh=torch.zeros(n, 1, 3),
    ).check()
    viewmats = []
    for dx in offsets:
        viewmat = np.eye(4)
        viewmat[:2, 3] = -dx, -abs(dx)
        viewmats.append(viewmat)
    K = [[20.0, 0.0, 10.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]]
    cameras = Cameras.from_lists(
        viewmats, [K] * len(stems), [20] * len(stems), [12] * len(stems), stems
    )
    return gaussians, cameras


def hand_frames() -> list[OpenHypeFrame]:
    """DSC00001 (20×12): chair in rows 0–5, columns 0–9 (60 of 240 pixels), a leg in rows
    6–11, columns 0–3; DSC00002 at twice the resolution (40×24): chair in the left half."""
    chair = rectangle(12, 20, (0, 6), (0, 10))
    leg = rectangle(12, 20, (6, 12), (0, 4))
    big_chair = rectangle(24, 40, (0, 24), (0, 20))
    return [
        frame(
            "DSC00001",
            [
                obj("chair", chair, [0, 0, 9, 5], path="1c.png"),
                obj("leg of a chair", leg, [0, 6, 3, 11], True, "1l.png"),
            ],
        ),
        frame("DSC00002", [obj("chair", big_chair, [0, 0, 19, 23], path="2c.png")], size=(40, 24)),
    ]


def test_the_protocol_by_hand():
    gaussians, cameras = wall_scene(["DSC00001.JPG", "DSC00002.JPG"], offsets=(0.0, 0.0))
    everything = np.ones(len(gaussians), dtype=bool)
    for size in ((20, 12), (40, 24)):
        opacity = selection_opacity(
            gaussians, cameras.resized([size[0]] * 2, [size[1]] * 2).select([0]), everything
        )
        assert (opacity > 0.5).all()  # the wall covers every pixel
    engine = Oracle({"chair": everything}, len(gaussians), paper={"leg of a chair": everything})
    result = evaluate_openhype(engine, gaussians, cameras, hand_frames())
    # IoU: 60 / 240, the leg selects nothing: 0; 480 / 960 at the mask's resolution
    assert [(i["frame"], i["prompt"], i["part"], i["iou"]) for i in result.items] == [
        ("DSC00001", "chair", False, 0.25),
        ("DSC00001", "leg of a chair", True, 0.0),
        ("DSC00002", "chair", False, 0.5),
    ]
    assert [i["predicted_pixels"] for i in result.items] == [240, 0, 960]
    # every pixel ties at the peak of a full prediction: a hit wherever the box is; none: a miss
    assert [i["localized"] for i in result.items] == [True, False, True]
    # flat over (frame, prompt), as OpenHype averages (per frame first would give 0.3125)
    assert result.metrics == {
        "miou": pytest.approx(0.75 / 3),
        "localization": pytest.approx(2 / 3),
        "miou_objects": 0.375,
        "localization_objects": 1.0,
        "miou_parts": 0.0,
        "localization_parts": 0.0,
    }
    assert result.settings["views"] == "name" and result.notes == ()
    assert (result.settings["object_prompts"], result.settings["part_prompts"]) == (2, 1)

    # the paper's rule is the engine's using(mode="paper"): here it selects the leg only
    paper = evaluate_openhype(
        engine.using(mode="paper", levels=None), gaussians, cameras, hand_frames()
    )
    assert paper.metrics["miou_parts"] == 24 / 240 and paper.metrics["miou_objects"] == 0.0
    assert paper.settings["selection"] == "paper"


def test_frames_without_a_view_and_of_another_shape_are_refused():
    gaussians, cameras = wall_scene(["DSC00001.JPG", "DSC00003.JPG"], offsets=(0.0, 0.0))
    engine = Oracle({}, len(gaussians))
    with pytest.raises(InputError) as caught:
        evaluate_openhype(engine, gaussians, cameras, hand_frames(), source="gt")
    assert str(caught.value) == (
        "gt/DSC00002.json: no view named 'DSC00002' (views: DSC00001, DSC00003)"
    )
    gaussians, cameras = wall_scene(["DSC00001.JPG", "DSC00002.JPG"], offsets=(0.0, 0.0))
    frames = hand_frames()
    frames[1] = frame(
        "DSC00002",
        [obj("chair", rectangle(40, 40, (0, 1), (0, 1)), [0, 0, 0, 0], path="x.png")],
        size=(40, 40),
    )
    with pytest.raises(
        InputError, match=r"gt/DSC00002\.json: labels are 40×40 but their camera is 20×12"
    ):
        evaluate_openhype(engine, gaussians, cameras, frames, source="gt")
    result = evaluate_openhype(engine, gaussians, cameras, frames, rescale_labels=True)
    assert len(result.items) == 3


def test_preprocessed_views_are_matched_by_the_order_of_the_files():
    """scannetpp_preprocess.py renames the annotated images frame_eval_00001 … in the sorted
    order of the annotation files; the cameras the frames state must agree."""
    # camera centres (dx, |dx|) of a scalene triangle: no relabelling of them is a similarity
    offsets = (-0.5, 0.0, 0.7)
    stems = ["frame_eval_00001", "frame_eval_00002", "frame_eval_00003", "frame_train_00001"]
    _, cameras = wall_scene([f"images/{s}.JPG" for s in stems], offsets=(*offsets, 0.2))
    frames = [
        frame(f"DSC0000{k}", [], dx=dx, dy=abs(dx)) for k, dx in zip((7, 3, 5), (0.7, -0.5, 0.0))
    ]
    match = openhype_views(cameras, frames, "gt")
    # DSC00003 → frame_eval_00001 (camera 0), DSC00005 → 00002, DSC00007 → 00003
    assert match.indices == (2, 0, 1) and match.rule == "frame_eval"
    assert "matched to the preprocessed test views frame_eval_00001 … frame_eval_00003" in (
        match.note
    )
    # a frame whose stated camera is another view's
    swapped = [frame(f.stem, [], dx=dx, dy=abs(dx)) for f, dx in zip(frames, (-0.5, 0.7, 0.0))]
    with pytest.raises(InputError, match="gt: the annotation files' cameras are not the scene's"):
        openhype_views(cameras, swapped, "gt")
    with pytest.raises(InputError, match="different intrinsics"):
        openhype_views(cameras, [frame(f.stem, [], size=(20, 20), dx=0.0) for f in frames], "gt")
    with pytest.raises(InputError) as caught:
        openhype_views(cameras, frames[:2], "gt")
    assert "test views are frame_eval_00001 … frame_eval_00003 (3) as scannetpp_preprocess.py" in (
        str(caught.value)
    )
    # the name rule wins where the images are the scene's views
    _, named = wall_scene(["DSC00003.JPG", "DSC00005.JPG", "DSC00007.JPG"], offsets)
    assert openhype_views(named, frames, "gt").indices == (2, 0, 1)
    with pytest.raises(InputError, match="gt: the scene has no cameras"):
        openhype_views(None, frames, "gt")


# ------------------------------------------------------------------ a synthetic scene


@pytest.fixture(scope="module")
def layout(small_dataset, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("openhype") / "data"
    write_openhype_scannetpp(small_dataset, root, SCENE, link=True)
    return root


def ground_truth_table(dataset: Path) -> dict[str, np.ndarray]:
    """Each prompt's Gaussians by the dataset's ground truth: objects by name, parts as
    "[PART] of a [OBJ]"."""
    hierarchy = read_hierarchy(dataset / "ground_truth.safetensors")
    labels, parents = hierarchy.labels, hierarchy.levels.parents
    table: dict[str, np.ndarray] = {}
    for node, name in enumerate(hierarchy.names[3]):
        table.setdefault(name, np.zeros(len(labels), bool))[labels[:, 3] == node] = True
    for node, name in enumerate(hierarchy.names[2]):
        prompt = part_prompt(name, hierarchy.names[3][parents[2][node]])
        table.setdefault(prompt, np.zeros(len(labels), bool))[labels[:, 2] == node] = True
    return table


def test_the_layout_is_a_preprocessed_scannetpp_scene(layout, small_dataset):
    data, annotations = (
        layout / "scannetpp" / SCENE,
        layout / "openhype_scannetpp_benchmark" / SCENE,
    )
    record = json.loads((small_dataset / "synthetic.json").read_text())
    evaluated = record["evaluation_views"]
    transforms = json.loads((data / "transforms.json").read_text())
    paths = [f["file_path"] for f in transforms["frames"]]
    count = len(evaluated)
    assert paths[:count] == [f"images/frame_eval_{k:05d}.jpg" for k in range(1, count + 1)]
    assert paths[count:] == [f"images/frame_train_{k:05d}.jpg" for k in range(1, 9 - count)]
    assert sorted(p.name for p in (data / "images").iterdir()) == sorted(
        Path(p).name for p in paths
    )
    # the renamed views are the evaluated images, in order
    first = np.asarray(Image.open(data / "images" / "frame_eval_00001.jpg"))
    np.testing.assert_array_equal(
        first, np.asarray(Image.open(small_dataset / "images" / f"{evaluated[0]}.jpg"))
    )
    assert (data / "language_features" / "frame_train_00001_s.npy").is_file()
    assert sorted(p.name for p in annotations.glob("*.json")) == [f"{s}.json" for s in evaluated]
    assert sorted(p.name for p in annotations.glob("*.jpg")) == [f"{s}.jpg" for s in evaluated]
    assert (layout / "output" / SCENE / "cfg_args").is_file()

    frames = read_openhype_annotations(annotations)
    prompts = {p.category: p.is_part for f in frames for p in f.prompts()}
    assert prompts["mug"] is False and prompts["handle of a mug"] is True
    assert prompts["table"] is False and "floor" not in prompts
    assert all(
        is_part == (" of a " in name and name != "stack of books")
        for name, is_part in prompts.items()
    )
    reference = reference_reading(annotations)
    for ours, theirs in zip(frames, reference):
        for prompt in ours.prompts():
            np.testing.assert_array_equal(prompt.mask, theirs[prompt.category]["mask"] == 1)
    # the stated cameras are the dataset's
    own = load_cameras(small_dataset)[0]
    for f in frames:
        index = own.stems.index(f.view)
        np.testing.assert_allclose(
            f.cameras().viewmats[0].numpy(), own.viewmats[index].numpy(), atol=1e-9
        )


@pytest.mark.slow
def test_the_ground_truth_selection_scores_high_and_a_wrong_one_low(layout, small_dataset):
    data = layout / "scannetpp" / SCENE
    scene = load_scene(layout / "output" / SCENE)
    assert scene.cameras.stems[0] == "frame_eval_00001"
    truth = find_ground_truth(data)
    assert truth.available() == ("openhype",)
    table = ground_truth_table(small_dataset)
    engine = Oracle(table, len(scene.gaussians))
    report = evaluate_dataset(truth, engine, scene.gaussians, scene.cameras)
    result = report.results[0]
    assert [r.protocol for r in report.results] == ["openhype", "openhype-paper"]
    assert result.settings["views"] == "frame_eval" and "frame_eval_00001" in result.notes[0]
    # opacity > 0.5 against each pixel's max-weight Gaussian: the few thousand Gaussians'
    # silhouettes are thinner than their footprint, so edges cost a little
    assert result.metrics["miou"] > 0.8 and result.metrics["localization"] > 0.95
    assert result.metrics["miou_objects"] > 0.8 and result.metrics["miou_parts"] > 0.75
    assert result.settings["part_prompts"] > result.settings["object_prompts"] > 10

    # each IoU is the evaluator's on the same prediction and its own reading of the masks
    frames = read_openhype_annotations(truth.path("openhype"))
    reference = reference_reading(truth.path("openhype"))
    from thgs.views import selection_masks

    for f, theirs in zip(frames[:1], reference[:1]):
        camera = scene.cameras.select([scene.cameras.stems.index("frame_eval_00001")])
        texts = [p.category for p in f.prompts()]
        predicted = selection_masks(scene.gaussians, camera, engine.selected(texts))
        items = [i for i in result.items if i["frame"] == f.stem]
        for q, (text, item) in enumerate(zip(texts, items)):
            assert item["iou"] == pytest.approx(
                reference_iou(predicted[..., q], theirs[text]["mask"])
            )

    # the same annotations in the dataset's own views (matched by name): the same scores
    own = load_scene(small_dataset)
    by_name = evaluate_openhype(engine, own.gaussians, own.cameras, frames)
    assert by_name.settings["views"] == "name"
    assert [i["iou"] for i in by_name.items] == [i["iou"] for i in result.items]

    # every prompt given another prompt's Gaussians
    prompts = sorted(table)
    shifted = {p: table[prompts[(k + 7) % len(prompts)]] for k, p in enumerate(prompts)}
    wrong = evaluate_openhype(
        Oracle(shifted, len(scene.gaussians)), scene.gaussians, scene.cameras, frames
    )
    assert wrong.metrics["miou"] < 0.2


@pytest.mark.slow
def test_the_suite_finds_the_layout_and_runs_the_protocol(layout, small_dataset, tmp_path):
    (scene,) = find_suite(layout)
    assert (scene.key, scene.protocols, scene.problems) == (f"openhype/{SCENE}", ("openhype",), ())
    assert scene.model == layout / "output" / SCENE
    assert scene.ground_truth.path("openhype") == layout / "openhype_scannetpp_benchmark" / SCENE
    assert scene.guidance == layout / "scannetpp" / SCENE / "language_features"
    loaded = load_scene(scene.model)
    engine = Oracle(ground_truth_table(small_dataset), len(loaded.gaussians))
    report = evaluate_dataset(
        scene.ground_truth, engine, loaded.gaussians, loaded.cameras, protocols=scene.protocols
    )
    assert report.metric("openhype", "miou") > 0.8

    # a processed scene in scannetpp/ without annotations: a scene whose problem says so
    root = tmp_path / "root"
    shutil.copytree(layout / "scannetpp", root / "scannetpp", symlinks=True)
    (bare,) = find_suite(root)
    assert bare.key == f"openhype/{SCENE}" and bare.protocols == ()
    assert bare.problems[0].startswith("missing its ground truth: OpenHype's ScanNet++ annotations")

    # the report's table
    metrics = {
        name: {"miou": 0.5, "miou_objects": 0.75, "miou_parts": 0.25, "localization": 1.0}
        for name in ("openhype", "openhype-paper")
    }
    result = SceneResult("openhype", SCENE, {"eval": "ran"}, metrics=metrics)
    suite = SuiteReport(
        (result,),
        {"selection": "auto", "device": "cpu", "sam": "s", "clip": "c"},
        {},
        "in-process",
        1.0,
    )
    table = suite.table("openhype")
    assert table["columns"] == [
        "mIoU (auto)",
        "object mIoU (auto)",
        "part mIoU (auto)",
        "mIoU (paper's rule)",
        "part mIoU (paper's rule)",
        "loc (auto)",
    ]
    assert table["mean"] == [0.5, 0.75, 0.25, 0.5, 0.25, 1.0]
    assert "## OpenHype ScanNet++" in suite.markdown()


def test_the_annotation_folder_is_found_beside_the_scenes_or_given(layout, tmp_path):
    data = layout / "scannetpp" / SCENE
    annotations = layout / "openhype_scannetpp_benchmark" / SCENE
    assert find_ground_truth(data).path("openhype") == annotations
    # given: the scene's folder, the folder of every scene, or the root holding it
    for given in (annotations, annotations.parent, layout):
        assert find_ground_truth(data, openhype=given).path("openhype") == annotations
    with pytest.raises(InputError, match="holds no OpenHype annotation files"):
        find_ground_truth(data, openhype=layout / "output")
    # beside the scene itself as well; both places at once are refused, naming both
    root = tmp_path / "root"
    (root / "scannetpp" / "openhype_scannetpp_benchmark").mkdir(parents=True)
    (root / "openhype_scannetpp_benchmark").mkdir()
    (root / "scannetpp" / SCENE).symlink_to(data, target_is_directory=True)
    (root / "openhype_scannetpp_benchmark" / SCENE).symlink_to(annotations)
    assert find_ground_truth(root / "scannetpp" / SCENE).path("openhype") == (
        root / "openhype_scannetpp_benchmark" / SCENE
    )
    other = root / "scannetpp" / "openhype_scannetpp_benchmark" / SCENE
    other.mkdir()
    (other / "x.json").write_text("{}")
    with pytest.raises(InputError, match="OpenHype annotations in two places"):
        find_ground_truth(root / "scannetpp" / SCENE)


def test_thgs_eval_takes_the_annotation_folder_by_flag(layout, small_dataset, small_field, capsys):
    from conftest import run_cli

    wrong = layout / "output"
    argv = ["eval", str(small_dataset), str(small_field), "--protocol", "openhype"]
    code, stdout, err = run_cli([*argv, "--openhype", str(wrong)], capsys)
    err = " ".join(err.split())
    assert code == 2 and stdout == "" and "holds no OpenHype annotation files" in err, err
    code, _, err = run_cli(argv, capsys)  # not beside the synthetic dataset: named, not guessed
    assert code == 2 and "openhype: its ground truth is not in the dataset" in " ".join(err.split())
