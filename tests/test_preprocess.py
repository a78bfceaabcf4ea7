"""Preprocessing: SAM/SAM 2 point prompts against transformers' own processing, the multi-level
mask generator against a stand-in model whose answers are known, LangSplat's layout, resuming
after a crash, and ``thgs preprocess`` with small random models."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from thgs.errors import InputError, ThgsError
from thgs.guidance import langsplat, load_guidance, read_embedding_space, read_view_guidance
from thgs.scene import Cameras

transformers = pytest.importorskip("transformers")

import tiny_models  # noqa: E402  (needs transformers)
from thgs.guidance.preprocess import (  # noqa: E402
    MANIFEST_FILE,
    CLIPImageEncoder,
    ImageJob,
    MaskGeneratorConfig,
    PointSegmenter,
    PreprocessConfig,
    crop_boxes,
    generate_masks,
    image_jobs,
    langsplat_size,
    mask_features,
    point_grid,
    preprocess_image,
    preprocess_images,
    segment_map,
)

CLIP_SPACE = "test/tiny-clip"


# --- the pieces of SAM's generator, by hand ------------------------------------------------------


def test_point_grid_is_cell_centres_row_by_row():
    grid = point_grid(2)
    np.testing.assert_allclose(grid, [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    assert point_grid(32).shape == (1024, 2)
    assert point_grid(32)[:, 0].min() == pytest.approx(1 / 64)


def test_crop_boxes_match_sams_layout_by_hand():
    # 400 × 300, one layer: overlap int(512/1500 · 300) = 102, crop sides ceil((102 + 400) / 2)
    # = 251 and ceil((102 + 300) / 2) = 201, starts 0 and 251 − 102 = 149 (x), 0 and 99 (y)
    boxes = crop_boxes(300, 400, 1, 512 / 1500)
    assert boxes == [
        ((0, 0, 400, 300), 0),
        ((0, 0, 251, 201), 1),
        ((0, 99, 251, 300), 1),
        ((149, 0, 400, 201), 1),
        ((149, 99, 400, 300), 1),
    ]
    assert crop_boxes(300, 400, 0, 512 / 1500) == [((0, 0, 400, 300), 0)]
    assert len(crop_boxes(300, 400, 2, 512 / 1500)) == 1 + 4 + 16


def test_langsplat_size_rules():
    assert langsplat_size(1920, 1440) == (1440, 1080)  # taller than 1080: scaled to 1080 tall
    assert langsplat_size(979, 546) == (979, 546)  # LERF's size: unchanged
    assert langsplat_size(1000, 750, target_width=400) == (400, 300)
    assert langsplat_size(1001, 751, target_width=500) == (500, 375)  # truncated, as the reference


def test_segment_map_paints_later_masks_over_earlier_ones():
    masks = torch.zeros((3, 4, 5), dtype=torch.bool)
    masks[0, :2, :3] = True
    masks[1, 1:3, 2:5] = True
    masks[2, 3, 0] = True
    expected = np.full((4, 5), -1)
    expected[:2, :3] = 10
    expected[1:3, 2:5] = 11
    expected[3, 0] = 12
    np.testing.assert_array_equal(segment_map(masks, first_id=10), expected)
    assert segment_map(torch.zeros((0, 2, 3), dtype=torch.bool)).tolist() == [[-1] * 3] * 2


# --- SAM and SAM 2 through transformers -----------------------------------------------------------


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("models")
    return {
        "sam": tiny_models.tiny_sam(root / "sam"),
        "sam2": tiny_models.tiny_sam2(root / "sam2"),
        "clip": tiny_models.tiny_clip(root / "clip"),
    }


def _random_image(height: int, width: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def test_sam_matches_transformers_processing(models):
    """Our torchvision-free SAM path equals transformers' PIL image processor, the model's forward
    and its mask post-processing."""
    from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil

    segmenter = PointSegmenter("tiny", models["sam"])
    assert (segmenter.kind, segmenter.input_size) == ("sam", 256)
    image = _random_image(48, 80, 0)
    points = torch.tensor([[3.0, 40.0], [79.0, 0.0], [41.5, 22.25]])
    embedded = segmenter.embed(image)
    low_res, iou = segmenter.decode(embedded, points)
    assert low_res.shape == (3, 3, 64, 64)  # 4 × the 16² image embedding
    logits = segmenter.upsample(low_res.flatten(0, 1), embedded).reshape(3, 3, 48, 80)
    assert logits.shape == (3, 3, 48, 80) and iou.shape == (3, 3)

    processor = SamImageProcessorPil(
        size={"longest_edge": 256}, pad_size={"height": 256, "width": 256}
    )
    inputs = processor(images=image, return_tensors="pt")
    assert inputs["reshaped_input_sizes"].tolist() == [[154, 256]]  # int(48 · 256/80 + 0.5)
    model = transformers.SamModel.from_pretrained(models["sam"]).eval()
    scale = torch.tensor([256 / 80, 154 / 48])
    with torch.no_grad():
        output = model(
            pixel_values=inputs["pixel_values"],
            input_points=(points * scale)[None, :, None, :],
            multimask_output=True,
        )
    expected = processor.post_process_masks(
        output.pred_masks, inputs["original_sizes"], inputs["reshaped_input_sizes"], binarize=False
    )[0]
    torch.testing.assert_close(logits, expected, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(iou, output.iou_scores[0], atol=1e-5, rtol=1e-5)


def test_sam2_resizes_to_the_square_and_scales_points_per_axis(models):
    segmenter = PointSegmenter("tiny", models["sam2"])
    assert (segmenter.kind, segmenter.input_size) == ("sam2", 256)
    image = _random_image(40, 72, 1)
    points = torch.tensor([[10.0, 30.0], [71.0, 2.0]])
    embedded = segmenter.embed(image)
    low_res, iou = segmenter.decode(embedded, points)
    logits = segmenter.upsample(low_res.flatten(0, 1), embedded).reshape(2, 3, 40, 72)

    # by hand: a 256 × 256 bilinear resize, ImageNet normalization, x · 256/72 and y · 256/40,
    # low-res logits straight to 40 × 72
    resized = np.asarray(Image.fromarray(image).resize((256, 256), Image.BILINEAR), np.float32)
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    pixels = torch.from_numpy(((resized / 255 - mean) / std).astype(np.float32)).permute(2, 0, 1)
    model = transformers.Sam2Model.from_pretrained(models["sam2"]).eval()
    with torch.no_grad():
        output = model(
            pixel_values=pixels[None],
            input_points=(points * torch.tensor([256 / 72, 256 / 40]))[None, :, None, :],
            multimask_output=True,
        )
    expected = F.interpolate(output.pred_masks[0], (40, 72), mode="bilinear", align_corners=False)
    torch.testing.assert_close(logits, expected, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(iou, output.iou_scores[0], atol=1e-5, rtol=1e-5)


def test_missing_weights_name_the_model_and_the_download(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(ThgsError, match=r"facebook/sam-vit-huge.*hf download facebook/sam-vit"):
        PointSegmenter()
    with pytest.raises(ThgsError, match=r"no config\.json"):
        PointSegmenter("x", tmp_path)


def test_a_checkpoint_that_is_not_sam_is_refused(models):
    with pytest.raises(ThgsError, match="'clip' checkpoint, expected SAM"):
        PointSegmenter("x", models["clip"])


# --- the generator, with a stand-in model whose answers are known ---------------------------------


class ColourSegmenter:
    """A stand-in for SAM: the image's colour channels are label maps (red: sub-part, green:
    part, blue: object; 0 = background), and a point's three masks are the pixels sharing its
    sub-part, part and object label, with logits ±10 and predicted IoU 0.95 (0 on background)."""

    kind = "colour-labels"
    name = "colour-labels"
    device = torch.device("cpu")

    def embed(self, image: np.ndarray) -> np.ndarray:
        return image

    def decode(self, image: np.ndarray, points: torch.Tensor):
        labels = torch.from_numpy(image.astype(np.int64)).permute(2, 0, 1)  # [3, h, w]
        xs, ys = points[:, 0].long(), points[:, 1].long()
        at_points = labels[:, ys, xs].T  # [P, 3]
        masks = labels[None] == at_points[:, :, None, None]
        masks &= at_points[:, :, None, None] > 0
        logits = torch.where(masks, 10.0, -10.0)
        return logits, torch.where(at_points > 0, 0.95, 0.0)

    def upsample(self, logits: torch.Tensor, image: np.ndarray) -> torch.Tensor:
        return logits  # decoded at the image's size already


def _labelled_scene() -> tuple[np.ndarray, dict[str, list[np.ndarray]]]:
    """A 400 × 300 label image and the masks every level should end with.

    Object A (x 30–129, y 30–109) has two parts (left, right halves), each of two sub-parts (top,
    bottom halves). Object B (x 220–349, y 150–259) is one part and one sub-part, with a 3 × 3
    hole and a 4 × 4 island far away, both under SAM's 100 px cleanup size.
    """
    image = np.zeros((300, 400, 3), dtype=np.uint8)
    image[30:110, 30:130, 2] = 1
    image[30:110, 30:80, 1] = 1
    image[30:110, 80:130, 1] = 2
    image[30:70, 30:80, 0], image[70:110, 30:80, 0] = 1, 2
    image[30:70, 80:130, 0], image[70:110, 80:130, 0] = 3, 4
    image[150:260, 220:350] = (5, 3, 2)
    b_whole = image[..., 2] == 2
    image[200:203, 280:283] = 0  # hole
    image[20:24, 380:384] = (5, 3, 2)  # island

    def region(channel: int, label: int) -> np.ndarray:
        return image[..., channel] == label

    a, parts = region(2, 1), [region(1, 1), region(1, 2)]
    subs = [region(0, k) for k in (1, 2, 3, 4)]
    expected = {
        "s": [*subs, b_whole],
        "m": [*parts, b_whole],
        "l": [a, b_whole],
        # pooled: each sub-part lies wholly in object A and covers a quarter of it, under
        # LangSplat's containment rule (≥ 0.85 inside, < 0.5 of the other) it is dropped; parts
        # cover half of A, so they stay; B's three identical masks are one after box NMS
        "default": [a, *parts, b_whole],
    }
    return image, expected


def _as_set(masks) -> set[bytes]:
    return {np.packbits(np.asarray(mask, dtype=bool)).tobytes() for mask in masks}


@pytest.mark.slow
@pytest.mark.parametrize("crop_layers", [0, 1])
def test_generator_recovers_known_masks_at_every_level(crop_layers):
    image, expected = _labelled_scene()
    config = MaskGeneratorConfig(points_per_side=16, crop_layers=crop_layers)
    levels = generate_masks(ColourSegmenter(), image, config)
    assert list(levels) == ["default", "s", "m", "l"]
    for name, masks in expected.items():
        level = levels[name]
        assert len(level) == len(masks), name
        assert _as_set(level.masks.numpy()) == _as_set(masks), name
        for mask, box in zip(level.masks.numpy(), level.boxes.tolist()):
            ys, xs = np.nonzero(mask)
            assert box == [xs.min(), ys.min(), xs.max(), ys.max()]
        np.testing.assert_allclose(level.predicted_iou.numpy(), 0.95)
        np.testing.assert_allclose(level.stability.numpy(), 1.0)


def test_without_the_cleanup_the_hole_and_island_stay():
    image, expected = _labelled_scene()
    config = MaskGeneratorConfig(points_per_side=16, crop_layers=0, min_region_area=0)
    level = generate_masks(ColourSegmenter(), image, config)["l"]
    b_as_drawn = image[..., 2] == 2
    assert _as_set(level.masks.numpy()) == _as_set([expected["l"][0], b_as_drawn])


def test_inner_crop_edges_drop_cut_masks():
    """A crop that cuts object B yields a B mask touching an inner crop edge; it is dropped, so
    only whole masks remain even when the whole-image crop has no prompt on B."""
    image, expected = _labelled_scene()
    # 2 points per side: the whole image's prompts (100, 75) etc. miss B; crops' prompts hit it
    config = MaskGeneratorConfig(points_per_side=2, crop_layers=1)
    level = generate_masks(ColourSegmenter(), image, config)["l"]
    for mask in level.masks.numpy():
        assert any(np.array_equal(mask, whole) for whole in expected["l"])


def test_a_level_without_masks_is_empty_and_paints_minus_one():
    image = np.zeros((40, 50, 3), dtype=np.uint8)  # all background: every prompt scores 0
    levels = generate_masks(ColourSegmenter(), image, MaskGeneratorConfig(points_per_side=4))
    assert all(len(level) == 0 for level in levels.values())
    assert (segment_map(levels["s"].masks) == -1).all()


# --- one image in LangSplat's layout -----------------------------------------------------------


@pytest.fixture(scope="module")
def clip(models) -> CLIPImageEncoder:
    return CLIPImageEncoder(CLIP_SPACE, models["clip"])


@pytest.mark.slow
def test_preprocess_image_writes_langsplat_ids_and_features(clip):
    image, expected = _labelled_scene()
    config = PreprocessConfig(masks=MaskGeneratorConfig(points_per_side=16, crop_layers=0))
    view = preprocess_image(image, "frame", ColourSegmenter(), clip, config)
    view.check()
    counts = [len(expected[name]) for name in langsplat.LEVELS]
    assert view.segments.shape == (4, 300, 400) and view.features.shape == (sum(counts), 16)
    offsets = np.cumsum([0, *counts])
    pixels = torch.from_numpy(image).float() / 255
    for k, name in enumerate(langsplat.LEVELS):
        ids = view.segments[k]
        covered = np.any(expected[name], axis=0)
        assert (ids[~covered] == -1).all()
        assert (ids[covered] >= offsets[k]).all() and (ids[covered] < offsets[k + 1]).all()
        rows = []
        for mask in expected[name]:
            # each known mask has one feature row: CLIP on its own crop
            ys, xs = np.nonzero(mask)
            box = torch.tensor([[xs.min(), ys.min(), xs.max(), ys.max()]])
            reference = mask_features(clip, pixels, torch.from_numpy(mask)[None], box)[0]
            distances = np.abs(view.features[offsets[k] : offsets[k + 1]] - reference).max(1)
            row = offsets[k] + int(np.argmin(distances))
            assert distances.min() < 1e-5
            # its id marks only its own pixels (later masks may paint over some of them)
            assert mask[ids == row].all()
            rows.append(row)
        assert sorted(rows) == list(range(offsets[k], offsets[k + 1]))
    # painting order: at level default, object A comes after its first part and covers it
    part, a = expected["default"][1], expected["default"][0]
    assert len(np.unique(view.segments[0][part])) == 1
    assert np.unique(view.segments[0][a]).size == 2
    np.testing.assert_allclose(np.linalg.norm(view.features, axis=1), 1.0, rtol=1e-5)


# --- folders: resumable, LangSplat-readable ------------------------------------------------------


def _image_folder(root: Path, count: int = 3, size: tuple[int, int] = (56, 40)) -> Path:
    folder = root / "images"
    folder.mkdir(parents=True)
    for i in range(count):
        Image.fromarray(_random_image(size[1], size[0], 10 + i)).save(folder / f"frame_{i:03d}.png")
    return folder


PERMISSIVE = PreprocessConfig(
    masks=MaskGeneratorConfig(
        points_per_side=4, pred_iou_threshold=0.0, stability_threshold=0.0, min_region_area=20
    ),
    clip_batch_size=5,
)


@pytest.mark.parametrize("sam", ["sam", "sam2"])
def test_random_models_end_to_end_write_langsplat_files(tmp_path, models, clip, sam):
    images = _image_folder(tmp_path)
    segmenter = PointSegmenter("tiny", models[sam])
    output = tmp_path / "language_features"
    summary = preprocess_images(image_jobs(images), output, segmenter, clip, PERMISSIVE)
    assert sorted(summary.done) == ["frame_000", "frame_001", "frame_002"]
    assert sum(summary.masks) > 0
    for stem in summary.done:
        # LangSplat's conventions with plain numpy: float32 [4, H, W] ids, −1 = none, level k's
        # ids after level k−1's, rows of _f.npy indexed by the ids
        segments = np.load(output / f"{stem}_s.npy")
        features = np.load(output / f"{stem}_f.npy")
        assert segments.dtype == np.float32 and segments.shape == (4, 40, 56)
        assert features.dtype == np.float32 and features.shape[1] == 16
        assert segments.min() >= -1 and segments.max() < len(features)
        previous = -1
        for level in segments:
            ids = np.unique(level[level >= 0]).astype(int)
            if len(ids):
                assert ids[0] > previous
                previous = ids[-1]
        np.testing.assert_allclose(np.linalg.norm(features, axis=1), 1.0, rtol=1e-5)
        assert read_view_guidance(output, stem).segments.shape == (4, 40, 56)
    assert read_embedding_space(output) == (CLIP_SPACE, 16)
    manifest = json.loads((output / MANIFEST_FILE).read_text())
    assert manifest["sam"] == str(models[sam]) and manifest["clip"] == CLIP_SPACE
    assert manifest["config"]["masks"]["points_per_side"] == 4

    # the library's reader, with cameras of the images' size
    cameras = Cameras.from_lists(
        viewmats=np.tile(np.eye(4), (3, 1, 1)),
        Ks=np.tile(np.array([[50.0, 0, 28], [0, 50, 20], [0, 0, 1]]), (3, 1, 1)),
        widths=np.full(3, 56),
        heights=np.full(3, 40),
        names=[f"frame_{i:03d}.png" for i in range(3)],
    )
    assert [view.stem for view in load_guidance(output, cameras)] == sorted(summary.done)


def test_default_thresholds_on_random_models_write_all_minus_one(tmp_path, models, clip):
    """A random SAM's scores fall under the reference's thresholds: every level is empty, and the
    files are still written (the reference crashes here)."""
    images = _image_folder(tmp_path, count=1)
    segmenter = PointSegmenter("tiny", models["sam"])
    config = PreprocessConfig(masks=MaskGeneratorConfig(points_per_side=4, crop_layers=0))
    output = tmp_path / "out"
    summary = preprocess_images(image_jobs(images), output, segmenter, clip, config)
    assert summary.masks == (0, 0, 0, 0)
    assert (np.load(output / "frame_000_s.npy") == -1).all()
    assert np.load(output / "frame_000_f.npy").shape == (0, 16)


@pytest.mark.slow
def test_a_crash_mid_write_resumes_to_identical_results(tmp_path, models, clip, monkeypatch):
    images = _image_folder(tmp_path)
    segmenter = PointSegmenter("tiny", models["sam"])
    jobs = image_jobs(images)
    reference = tmp_path / "uninterrupted"
    preprocess_images(jobs, reference, segmenter, clip, PERMISSIVE)

    output = tmp_path / "interrupted"
    real_atomic_output = langsplat.atomic_output

    @contextlib.contextmanager
    def crash_on_second_masks(path, mode="wb"):
        with real_atomic_output(path, mode) as handle:
            if Path(path).name == "frame_001_s.npy":
                handle.write(b"\x93NUMPY half a file")
                raise KeyboardInterrupt("simulated crash while writing frame_001_s.npy")
            yield handle

    monkeypatch.setattr(langsplat, "atomic_output", crash_on_second_masks)
    with pytest.raises(KeyboardInterrupt):
        preprocess_images(jobs, output, segmenter, clip, PERMISSIVE)
    monkeypatch.setattr(langsplat, "atomic_output", real_atomic_output)
    names = sorted(path.name for path in output.iterdir())
    # frame_000 finished, frame_001's features written but not its masks, no temporary files
    assert names == [
        "embedding.json",
        "frame_000_f.npy",
        "frame_000_s.npy",
        "frame_001_f.npy",
        MANIFEST_FILE,
    ]

    seen = []
    summary = preprocess_images(
        jobs, output, segmenter, clip, PERMISSIVE, on_image=lambda stem, s: seen.append((stem, s))
    )
    assert summary.skipped == ["frame_000"] and sorted(summary.done) == ["frame_001", "frame_002"]
    assert seen[0] == ("frame_000", None)
    for path in reference.iterdir():
        assert (output / path.name).read_bytes() == path.read_bytes(), path.name


def test_other_settings_or_foreign_files_are_refused(tmp_path, models, clip):
    images = _image_folder(tmp_path, count=1)
    segmenter = PointSegmenter("tiny", models["sam"])
    output = tmp_path / "lf"
    preprocess_images(image_jobs(images), output, segmenter, clip, PERMISSIVE)
    other = PreprocessConfig(masks=MaskGeneratorConfig(points_per_side=8))
    with pytest.raises(InputError, match=r"preprocess\.json: this folder was preprocessed with"):
        preprocess_images(image_jobs(images), output, segmenter, clip, other)
    summary = preprocess_images(image_jobs(images), output, segmenter, clip, other, overwrite=True)
    assert list(summary.done) == ["frame_000"]
    assert json.loads((output / MANIFEST_FILE).read_text())["config"]["masks"]["points_per_side"]

    foreign = tmp_path / "langsplat_made"
    foreign.mkdir()
    np.save(foreign / "frame_000_s.npy", np.full((4, 40, 56), -1, np.float32))
    with pytest.raises(InputError, match="made by another tool"):
        preprocess_images(image_jobs(images), foreign, segmenter, clip, PERMISSIVE)


def test_image_jobs_sizes_and_errors(tmp_path, clip):
    images = _image_folder(tmp_path, count=2, size=(100, 60))
    Image.fromarray(_random_image(10, 10, 0)).save(images / "frame_000.jpg")
    with pytest.raises(InputError, match=r"share a name stem: \['frame_000'\]"):
        image_jobs(images)
    (images / "frame_000.jpg").unlink()
    (images / "notes.txt").write_text("not an image")
    jobs = image_jobs(images)
    assert [(job.stem, job.size) for job in jobs] == [("frame_000", None), ("frame_001", None)]
    assert [job.size for job in image_jobs(images, target_width=50)] == [(50, 30), (50, 30)]

    cameras = Cameras.from_lists(
        viewmats=np.tile(np.eye(4), (1, 1, 1)),
        Ks=np.array([[[40.0, 0, 40], [0, 40, 25], [0, 0, 1]]]),
        widths=np.array([80]),
        heights=np.array([50]),
        names=["frame_001"],
    )
    assert image_jobs(images, cameras=cameras) == [
        ImageJob(images / "frame_001.png", "frame_001", (80, 50))
    ]
    with pytest.raises(InputError, match="either cameras or an explicit width"):
        image_jobs(images, cameras=cameras, target_width=10)
    missing = Cameras.from_lists(
        viewmats=cameras.viewmats, Ks=cameras.Ks, widths=[80], heights=[50], names=["frame_9"]
    )
    with pytest.raises(InputError, match=r"no image for 1 of 1 cameras \(first: \['frame_9'\]\)"):
        image_jobs(images, cameras=missing)
    with pytest.raises(InputError, match="image folder not found"):
        image_jobs(tmp_path / "nowhere")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match=r"no \.png/\.jpg/\.jpeg images"):
        image_jobs(empty)
    (images / "broken.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match=r"broken\.png: not a readable image"):
        preprocess_images(
            [ImageJob(images / "broken.png", "broken")], tmp_path / "x", ColourSegmenter(), clip
        )


# --- thgs preprocess ------------------------------------------------------------------------------


def _cli(argv: list[str], capsys) -> tuple[int, str, str]:
    from thgs.cli import entrypoint

    try:
        entrypoint(argv)
        code = 0
    except SystemExit as exit_:
        code = int(exit_.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, " ".join(captured.err.split())


def test_cli_preprocesses_a_folder_and_resumes(tmp_path, models, capsys):
    _image_folder(tmp_path, count=2)
    argv = [
        "preprocess",
        str(tmp_path),
        "--sam",
        str(models["sam2"]),
        "--clip",
        str(models["clip"]),
        "--space",
        CLIP_SPACE,
        "--points-per-side",
        "4",
    ]
    code, out, err = _cli(argv, capsys)
    assert code == 0, err
    assert "done 2, skipped 0 finished" in " ".join(out.split())
    output = tmp_path / "language_features"
    assert read_embedding_space(output) == (CLIP_SPACE, 16)
    for stem in ("frame_000", "frame_001"):
        assert read_view_guidance(output, stem).segments.shape == (4, 40, 56)
    code, out, _ = _cli(argv, capsys)
    assert code == 0 and "done 0, skipped 2 finished" in " ".join(out.split())


def test_cli_masks_at_the_cameras_size(tmp_path, models, capsys):
    from thgs.scene import write_cameras_json

    _image_folder(tmp_path, count=2, size=(112, 80))
    cameras = Cameras.from_lists(
        viewmats=np.tile(np.eye(4), (1, 1, 1)),
        Ks=np.array([[[50.0, 0, 28], [0, 50, 20], [0, 0, 1]]]),
        widths=[56],
        heights=[40],
        names=["frame_001"],
    )
    write_cameras_json(tmp_path / "model" / "cameras.json", cameras)
    argv = ["preprocess", str(tmp_path), "--sam", str(models["sam"]), "--clip"]
    argv += [str(models["clip"]), "--cameras", str(tmp_path / "model"), "--points-per-side", "2"]
    code, _, err = _cli(argv, capsys)
    assert code == 0, err
    names = sorted(path.name for path in (tmp_path / "language_features").glob("*.npy"))
    assert names == ["frame_001_f.npy", "frame_001_s.npy"]
    assert np.load(tmp_path / "language_features" / "frame_001_s.npy").shape == (4, 40, 56)


def test_cli_names_missing_weights(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    _image_folder(tmp_path, count=1)
    code, _, err = _cli(["preprocess", str(tmp_path)], capsys)
    assert code == 2
    assert "SAM weights for 'facebook/sam-vit-huge' not found in the Hugging Face cache" in err
    assert "hf download facebook/sam-vit-huge" in err
    code, _, err = _cli(["preprocess", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and "image folder not found" in err


def _label_images(root: Path, count: int = 2) -> None:
    """Label images for :class:`ColourSegmenter`: a 20 × 16 object of two parts on background."""
    folder = root / "images"
    folder.mkdir(parents=True)
    for i in range(count):
        image = np.zeros((40, 56, 3), dtype=np.uint8)
        image[10:26, 10 + i : 30 + i] = (1, 1, 1)
        image[10:26, 20 + i : 30 + i, :2] = 2
        Image.fromarray(image).save(folder / f"frame_{i:03d}.png")


def test_cli_reaches_sams_thresholds_and_warns_without_masks(tmp_path, models, monkeypatch, capsys):
    import thgs.guidance.preprocess.models as preprocess_module

    monkeypatch.setattr(preprocess_module, "PointSegmenter", lambda *_, **__: ColourSegmenter())
    _label_images(tmp_path)
    argv = ["preprocess", str(tmp_path), "--clip", str(models["clip"]), "--points-per-side", "8"]
    argv += ["--min-region-area", "0"]
    code, out, err = _cli(argv, capsys)
    assert code == 0, err
    assert "warning" not in err and "without a mask" not in out
    manifest = json.loads((tmp_path / "language_features" / MANIFEST_FILE).read_text())
    assert manifest["config"]["masks"]["min_region_area"] == 0
    # the stand-in's predicted IoU is 0.95: a stricter threshold keeps no mask at all
    code, out, err = _cli([*argv, "--pred-iou-threshold", "0.96", "--overwrite"], capsys)
    assert code == 0, err
    assert "2 of 2 images without a mask (first: frame_000)" in " ".join(out.split())
    assert err.startswith("warning: ")
    assert "SAM kept no mask in 2 of 2 images (first: frame_000)" in err
    assert "--pred-iou-threshold (now 0.96), --stability-threshold (now 0.85)" in err
    views = [read_view_guidance(tmp_path / "language_features", f"frame_00{i}") for i in (0, 1)]
    assert all(len(view.features) == 0 for view in views)


class InterruptedSegmenter(ColourSegmenter):
    """:class:`ColourSegmenter`, and Ctrl-C when it decodes prompts in its second image."""

    def __init__(self) -> None:
        self.images = 0

    def embed(self, image: np.ndarray) -> np.ndarray:
        self.images += 1
        return image

    def decode(self, image: np.ndarray, points: torch.Tensor):
        if self.images == 2:
            raise KeyboardInterrupt
        return super().decode(image, points)


def test_cli_ctrl_c_mid_image_resumes_to_identical_files(tmp_path, models, monkeypatch, capsys):
    """Ctrl-C while SAM works on the second image: exit 130 and one error line; the first
    view's files stay (a view is finished when its _s.npy exists), the second leaves no file
    and no temporary, and the same command run again ends with the bytes of an uninterrupted
    run."""
    import thgs.guidance.preprocess.models as preprocess_module

    _label_images(tmp_path, count=3)
    argv = ["preprocess", str(tmp_path), "--clip", str(models["clip"]), "--points-per-side", "4"]
    argv += ["--crop-layers", "0", "--min-region-area", "0"]  # one SAM image per view
    reference = tmp_path / "uninterrupted"
    monkeypatch.setattr(preprocess_module, "PointSegmenter", lambda *_, **__: ColourSegmenter())
    code, _, err = _cli([*argv, "-o", str(reference)], capsys)
    assert code == 0, err

    monkeypatch.setattr(
        preprocess_module, "PointSegmenter", lambda *_, **__: InterruptedSegmenter()
    )
    code, out, err = _cli(argv, capsys)
    assert code == 130 and err.endswith("error: interrupted") and err.count("error:") == 1, err
    output = tmp_path / "language_features"
    assert sorted(path.name for path in output.iterdir()) == [
        "embedding.json",
        "frame_000_f.npy",
        "frame_000_s.npy",
        MANIFEST_FILE,
    ]
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "images",
        "language_features",
        "uninterrupted",
    ]

    monkeypatch.setattr(preprocess_module, "PointSegmenter", lambda *_, **__: ColourSegmenter())
    code, out, err = _cli(argv, capsys)
    assert code == 0, err
    assert "done 2, skipped 1 finished" in " ".join(out.split())
    files = sorted(path.name for path in reference.iterdir())
    assert sorted(path.name for path in output.iterdir()) == files
    assert len(files) == 3 * 2 + 2
    for name in files:
        assert (output / name).read_bytes() == (reference / name).read_bytes(), name


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [
        ("--pred-iou-threshold", "1.5", "must be in [0, 1], got 1.5"),
        ("--stability-threshold", "-0.1", "must be in [0, 1], got -0.1"),
        ("--min-region-area", "-1", "must be an integer ≥ 0, got -1"),
        ("--points-per-side", "0", "must be an integer ≥ 1, got 0"),
    ],
)
def test_cli_names_a_bad_threshold_by_its_flag(tmp_path, capsys, flag, value, message):
    _image_folder(tmp_path, count=1)
    code, _, err = _cli(["preprocess", str(tmp_path), flag, value], capsys)
    assert code == 2 and err == f"error: {flag}: {message}"


def test_mask_generator_config_names_the_setting():
    with pytest.raises(InputError, match=r"^stability_threshold: must be in \[0, 1\], got 2"):
        MaskGeneratorConfig(stability_threshold=2)
    with pytest.raises(InputError, match=r"^crop_layers: must be an integer ≥ 0, got -1"):
        MaskGeneratorConfig(crop_layers=-1)


def test_a_clip_folder_records_its_own_space_and_itself(tmp_path, models, monkeypatch, capsys):
    import thgs.guidance.preprocess.models as preprocess_module
    from thgs.guidance import read_embedding_model

    monkeypatch.setattr(preprocess_module, "PointSegmenter", lambda *_, **__: ColourSegmenter())
    _label_images(tmp_path, count=1)
    argv = ["preprocess", str(tmp_path), "--clip", str(models["clip"]), "--points-per-side", "4"]
    code, out, err = _cli(argv, capsys)
    assert code == 0, err
    output = tmp_path / "language_features"
    folder = str(models["clip"].resolve())
    # a folder with no Hugging Face id is a space of its own, at its real dimension (16, not
    # LangSplat's 512), and the features remember where the model is
    assert read_embedding_space(output) == (folder, 16)
    assert read_embedding_model(output) == models["clip"].resolve()
    assert f"CLIP {folder} (16-D)" in " ".join(out.split())
    # naming it LangSplat's space is refused: that model is 512-D
    argv += ["--space", "laion/CLIP-ViT-B-16-laion2B-s34B-b88K", "-o", str(tmp_path / "other")]
    code, _, err = _cli(argv, capsys)
    assert code == 2
    assert "projects to 16-D but laion/CLIP-ViT-B-16-laion2B-s34B-b88K is 512-D" in err
    code, _, err = _cli(["preprocess", str(tmp_path), "--space", "my/space"], capsys)
    assert code == 2 and "--space: names the space of a --clip folder" in err
