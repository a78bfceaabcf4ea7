"""Per-mask CLIP features: the batched crops against a slow numpy reference of LangSplat's steps
(with the inclusive box), hand-computed crops, and the image encoder on a randomly initialised
small CLIP against the model's own image features."""

from __future__ import annotations

import ast
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from thgs.errors import InputError, ThgsError
from thgs.guidance.preprocess.clip_features import (
    CLIP_MEAN,
    CLIP_STD,
    CLIPImageEncoder,
    mask_crops,
    mask_features,
)

transformers = pytest.importorskip("transformers")

import tiny_models  # noqa: E402  (needs transformers)

SPACE = "test/tiny-clip"


# --- the slow reference ---------------------------------------------------------------------


def resize_linear(square: np.ndarray, size: int) -> np.ndarray:
    """cv2.resize(square, (size, size), interpolation=cv2.INTER_LINEAR) on a float image, written
    out: output pixel u reads source coordinate (u + 0.5) · L / size − 0.5, clamped to
    [0, L − 1], and mixes its two neighbours linearly; rows first, then columns."""
    side = square.shape[0]

    def along_first_axis(array: np.ndarray) -> np.ndarray:
        out = np.zeros((size, *array.shape[1:]), dtype=np.float64)
        for u in range(size):
            s = (u + 0.5) * side / size - 0.5
            s = min(max(s, 0.0), side - 1.0)
            i = math.floor(s)
            t = s - i
            j = min(i + 1, side - 1)
            out[u] = (1 - t) * array[i] + t * array[j]
        return out

    rows = along_first_axis(square)  # [size, L, 3]
    return along_first_axis(rows.transpose(1, 0, 2)).transpose(1, 0, 2)  # [size, size, 3]


def reference_crop(image: np.ndarray, mask: np.ndarray, box, size: int) -> np.ndarray:
    """LangSplat's get_seg_img + pad_img + cv2.resize for one mask, with the inclusive box:
    [size, size, 3] float64."""
    x0, y0, x1, y1 = (int(v) for v in box)
    cut = image.astype(np.float64).copy()
    cut[~mask] = 0
    crop = cut[y0 : y1 + 1, x0 : x1 + 1]
    h, w = crop.shape[:2]
    side = max(w, h)
    square = np.zeros((side, side, 3))
    if h > w:
        square[:, (h - w) // 2 : (h - w) // 2 + w] = crop
    else:
        square[(w - h) // 2 : (w - h) // 2 + h, :] = crop
    return resize_linear(square, size)


def reference_crops(image, masks, boxes, size) -> np.ndarray:
    """[n, 3, size, size] float64."""
    return np.stack(
        [reference_crop(image, m, b, size).transpose(2, 0, 1) for m, b in zip(masks, boxes)]
    )


def bbox(mask: np.ndarray) -> list[int]:
    """Inclusive (x0, y0, x1, y1) of a non-empty mask."""
    ys, xs = np.nonzero(mask)
    return [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]


def random_masks(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """Blobs, single pixels (corner and interior), the full image, wide and tall strips at the
    image's edges (their squares reach outside the image), a sparse scatter, small and large."""
    yy, xx = np.mgrid[:height, :width]
    masks = []
    for _ in range(3):  # blobs of random radius
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        r = rng.uniform(2, 12)
        masks.append((yy - cy) ** 2 + ((xx - cx) / 1.5) ** 2 < r**2)
    for y, x in ((0, 0), (height - 1, width - 1), (height // 2, width // 3)):
        single = np.zeros((height, width), bool)
        single[y, x] = True
        masks.append(single)
    masks.append(np.ones((height, width), bool))
    wide = np.zeros((height, width), bool)
    wide[height - 3 :, 2:] = True  # wide strip at the bottom edge
    masks.append(wide)
    tall = np.zeros((height, width), bool)
    tall[1:, :2] = True  # tall strip at the left edge
    masks.append(tall)
    masks.append(rng.random((height, width)) < 0.3)  # holes everywhere
    small = np.zeros((height, width), bool)
    small[10:14, 20:23] = rng.random((4, 3)) < 0.7
    small[10, 20] = small[13, 22] = True
    masks.append(small)
    return np.stack([m for m in masks if m.any()])


def random_case(seed: int, height: int = 37, width: int = 53):
    rng = np.random.default_rng(seed)
    image = rng.random((height, width, 3)).astype(np.float32)
    masks = random_masks(height, width, rng)
    boxes = np.array([bbox(m) for m in masks], dtype=np.int64)
    return image, masks, boxes


def as_tensors(image, masks, boxes):
    return torch.from_numpy(image), torch.from_numpy(masks), torch.from_numpy(boxes)


# --- the reference itself ---------------------------------------------------------------------


def test_reference_resize_is_bilinear_with_half_pixel_centres():
    """The test's own resize agrees with torch's bilinear (align_corners=False), which samples
    like cv2's INTER_LINEAR, for down- and upscaling."""
    rng = np.random.default_rng(1)
    for side, size in ((13, 5), (5, 13), (7, 7), (448, 224)):
        square = rng.random((side, side, 3))
        expected = torch.nn.functional.interpolate(
            torch.from_numpy(square).permute(2, 0, 1)[None],
            size=(size, size),
            mode="bilinear",
            align_corners=False,
            antialias=False,
        )[0].permute(1, 2, 0)
        np.testing.assert_allclose(resize_linear(square, size), expected.numpy(), atol=1e-12)
    # exact 2x downscale: the mean of each 2 × 2 block (what cv2 computes with INTER_AREA then)
    square = rng.random((8, 8, 3))
    blocks = square.reshape(4, 2, 4, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(resize_linear(square, 4), blocks, atol=1e-12)


# --- mask_crops -------------------------------------------------------------------------------


@pytest.mark.parametrize(("seed", "size"), [(0, 16), (1, 24), (2, 5), (3, 64)])
def test_crops_match_the_slow_reference(seed, size):
    image, masks, boxes = random_case(seed)
    crops = mask_crops(*as_tensors(image, masks, boxes), size=size)
    assert crops.shape == (len(masks), 3, size, size) and crops.dtype == torch.float32
    expected = reference_crops(image, masks, boxes, size)
    np.testing.assert_allclose(crops.numpy(), expected, atol=1e-5, rtol=0)
    assert crops.min() >= 0 and crops.max() <= 1


def test_crops_at_the_default_size_match_the_reference():
    image, masks, boxes = random_case(4, height=300, width=260)
    keep = [0, 3, 6, 7, 8]  # a blob, a single pixel, the whole image (L = 300 > 224), strips
    masks, boxes = masks[keep], boxes[keep]
    crops = mask_crops(*as_tensors(image, masks, boxes))
    assert crops.shape == (5, 3, 224, 224)
    np.testing.assert_allclose(crops.numpy(), reference_crops(image, masks, boxes, 224), atol=1e-5)


def test_crops_of_a_constant_rectangle_are_known():
    colour = torch.tensor([0.2, 0.4, 0.6])
    image = colour.expand(12, 12, 3).clone()
    mask = torch.zeros(1, 12, 12, dtype=torch.bool)
    mask[0, 3:7, 2:10] = True  # x 2…9 (w = 8), y 3…6 (h = 4): L = 8, rows padded by 2 on top
    box = torch.tensor([[2, 3, 9, 6]])

    # at the square's own size the resize is the identity: 2 zero rows, 4 colour rows, 2 zero rows
    crop = mask_crops(image, mask, box, size=8)[0]
    rows = torch.tensor([0, 0, 1, 1, 1, 1, 0, 0], dtype=torch.float32)
    torch.testing.assert_close(crop, colour[:, None, None] * rows[None, :, None].expand(3, 8, 8))

    # doubled: output row v samples square row v / 2 − 1/4, so the edges blend over two rows
    crop = mask_crops(image, mask, box, size=16)[0]
    profile = [0, 0, 0, 0.25, 0.75, 1, 1, 1, 1, 1, 1, 0.75, 0.25, 0, 0, 0]
    expected = colour[:, None, None] * torch.tensor(profile)[None, :, None].expand(3, 16, 16)
    torch.testing.assert_close(crop, expected)

    # halved: output row v averages square rows 2v and 2v + 1
    crop = mask_crops(image, mask, box, size=4)[0]
    expected = colour[:, None, None] * torch.tensor([0, 1, 1, 0.0])[None, :, None].expand(3, 4, 4)
    torch.testing.assert_close(crop, expected)


def test_odd_padding_puts_the_extra_column_after_the_crop():
    image = torch.ones(10, 10, 3)
    mask = torch.zeros(1, 10, 10, dtype=torch.bool)
    mask[0, 2:8, 4:7] = True  # w = 3, h = 6: L = 6, (L − w) // 2 = 1 column before, 2 after
    crop = mask_crops(image, mask, torch.tensor([[4, 2, 6, 7]]), size=6)[0]
    columns = torch.tensor([0, 1, 1, 1, 0, 0], dtype=torch.float32)
    torch.testing.assert_close(crop, columns.expand(3, 6, 6))


def test_the_whole_inclusive_box_is_cropped():
    """A single pixel fills the whole crop (the reference's XYWH slicing would leave it empty),
    and a mask's last row and column are kept."""
    image = torch.rand(9, 11, 3)
    mask = torch.zeros(2, 9, 11, dtype=torch.bool)
    mask[0, 4, 7] = True
    mask[1, 2:5, 3:6] = True  # a 3 × 3 square: the crop is the image's pixels, unpadded
    crops = mask_crops(image, mask, torch.tensor([[7, 4, 7, 4], [3, 2, 5, 4]]), size=3)
    torch.testing.assert_close(crops[0], image[4, 7][:, None, None].expand(3, 3, 3))
    torch.testing.assert_close(crops[1], image[2:5, 3:6].permute(2, 0, 1))


def test_pixels_outside_the_mask_or_box_are_zero():
    image = torch.ones(6, 6, 3)
    mask = torch.ones(1, 6, 6, dtype=torch.bool)
    mask[0, 2, 2] = False  # a hole
    # a box smaller than the mask: the rest of the mask is cut off, as in the reference
    crop = mask_crops(image, mask, torch.tensor([[1, 1, 3, 3]]), size=3)[0]
    expected = torch.ones(3, 3, 3)
    expected[:, 1, 1] = 0
    torch.testing.assert_close(crop, expected)


def test_no_masks_give_no_crops():
    crops = mask_crops(
        torch.rand(5, 6, 3),
        torch.zeros(0, 5, 6, dtype=torch.bool),
        torch.zeros(0, 4, dtype=torch.int64),
        size=8,
    )
    assert crops.shape == (0, 3, 8, 8) and crops.dtype == torch.float32


def test_bad_inputs_are_named():
    image, masks, boxes = as_tensors(*random_case(0, height=20, width=30))
    with pytest.raises(InputError, match=r"^image: expected shape \[H, W, 3\], got \[3, 20, 30\]"):
        mask_crops(image.permute(2, 0, 1), masks, boxes)
    with pytest.raises(InputError, match=r"^image: expected floating-point .* torch.uint8"):
        mask_crops((image * 255).to(torch.uint8), masks, boxes)
    with pytest.raises(
        InputError, match=r"^masks: expected shape \[n, 20, 30\].*got \[\d+, 30, 20\]"
    ):
        mask_crops(image, masks.transpose(1, 2), boxes)
    with pytest.raises(InputError, match=r"^masks: expected dtype torch.bool, got torch.uint8"):
        mask_crops(image, masks.to(torch.uint8), boxes)
    with pytest.raises(InputError, match=r"^boxes: expected shape \[\d+, 4\]"):
        mask_crops(image, masks, boxes[:-1])
    with pytest.raises(
        InputError, match=r"^boxes: expected integer pixel corners, got dtype torch.float32"
    ):
        mask_crops(image, masks, boxes.float())
    bad = boxes.clone()
    bad[1] = torch.tensor([5, 2, 30, 4])  # x1 = W
    with pytest.raises(InputError, match=r"^boxes: box 1 is \[5, 2, 30, 4\].*x1 < 30"):
        mask_crops(image, masks, bad)
    bad[1] = torch.tensor([5, 4, 7, 3])  # y1 < y0
    with pytest.raises(InputError, match=r"^boxes: box 1 is \[5, 4, 7, 3\]"):
        mask_crops(image, masks, bad)
    with pytest.raises(InputError, match=r"^masks: expected a torch.Tensor, got ndarray"):
        mask_crops(image, masks.numpy(), boxes)
    with pytest.raises(InputError, match=r"^size: expected a positive int, got 0"):
        mask_crops(image, masks, boxes, size=0)
    with pytest.raises(InputError, match=r"one device, got cpu, meta and cpu"):
        mask_crops(image, masks.to("meta"), boxes)  # meta: a second device without a GPU


# --- the image encoder ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    return tiny_models.tiny_clip(tmp_path_factory.mktemp("tiny-clip"), image_size=32)


@pytest.fixture(scope="module")
def encoder(tiny_clip) -> CLIPImageEncoder:
    return CLIPImageEncoder(space=SPACE, model_path=tiny_clip)


@pytest.fixture(scope="module")
def model(tiny_clip):
    return transformers.CLIPModel.from_pretrained(tiny_clip).eval()


def by_hand(model, pixels: np.ndarray) -> np.ndarray:
    """CLIP's image feature of [n, 3, S, S] pixels in [0, 1]: normalize with CLIP's mean and
    std, the vision tower's pooled (layer-normed class token) output, the visual projection, then
    unit length."""
    mean = np.array(CLIP_MEAN).reshape(1, 3, 1, 1)
    std = np.array(CLIP_STD).reshape(1, 3, 1, 1)
    normalized = torch.from_numpy(((pixels - mean) / std).astype(np.float32))
    with torch.no_grad():
        pooled = model.vision_model(pixel_values=normalized).pooler_output
        features = model.visual_projection(pooled).numpy()
    return features / np.linalg.norm(features, axis=1, keepdims=True)


def test_encoder_reads_the_model_config(encoder):
    assert (encoder.space, encoder.dim, encoder.image_size) == (SPACE, 16, 32)
    assert encoder.device == torch.device("cpu")


def test_encode_gives_the_models_normalized_image_features(encoder, model):
    pixels = np.random.default_rng(5).random((3, 3, 32, 32))
    features = encoder.encode(torch.from_numpy(pixels).float())
    assert features.shape == (3, 16) and features.dtype == torch.float32
    np.testing.assert_allclose(features.norm(dim=1).numpy(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(features.numpy(), by_hand(model, pixels), rtol=1e-4, atol=1e-5)
    # the rows differ (a model that ignored its input would pass the comparison above)
    assert np.abs(features[0].numpy() - features[1].numpy()).max() > 1e-2
    assert encoder.encode(torch.zeros(0, 3, 32, 32)).shape == (0, 16)


def test_encode_checks_the_input_size(encoder):
    with pytest.raises(
        InputError, match=r"^pixels: expected shape \[n, 3, 32, 32\].*\[2, 3, 224, 224\]"
    ):
        encoder.encode(torch.zeros(2, 3, 224, 224))
    with pytest.raises(InputError, match=r"^pixels: expected floating-point"):
        encoder.encode(torch.zeros(2, 3, 32, 32, dtype=torch.uint8))


def test_encoder_in_another_dtype_returns_float32(tiny_clip, model):
    encoder = CLIPImageEncoder(space=SPACE, model_path=tiny_clip, dtype=torch.float64)
    pixels = np.random.default_rng(6).random((2, 3, 32, 32))
    features = encoder.encode(torch.from_numpy(pixels).float())
    assert features.dtype == torch.float32
    np.testing.assert_allclose(features.numpy(), by_hand(model, pixels), rtol=1e-4, atol=1e-5)


def test_mask_features_encode_the_reference_crops(encoder, model):
    image, masks, boxes = random_case(7)
    features = mask_features(encoder, *as_tensors(image, masks, boxes))
    assert features.shape == (len(masks), 16) and features.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(features, axis=1), 1.0, rtol=1e-6)
    expected = by_hand(model, reference_crops(image, masks, boxes, 32))
    np.testing.assert_allclose(features, expected, rtol=1e-4, atol=1e-5)

    for batch_size in (1, 3, 1000):
        again = mask_features(encoder, *as_tensors(image, masks, boxes), batch_size=batch_size)
        np.testing.assert_allclose(again, features, rtol=1e-5, atol=1e-6)


def test_mask_features_of_no_masks(encoder):
    features = mask_features(
        encoder,
        torch.rand(8, 9, 3),
        torch.zeros(0, 8, 9, dtype=torch.bool),
        torch.zeros(0, 4, dtype=torch.int64),
    )
    assert features.shape == (0, 16) and features.dtype == np.float32
    with pytest.raises(InputError, match=r"^batch_size: expected a positive int, got 0"):
        mask_features(
            encoder,
            torch.rand(8, 9, 3),
            torch.zeros(0, 8, 9, dtype=torch.bool),
            torch.zeros(0, 4, dtype=torch.int64),
            batch_size=0,
        )


def test_missing_clip_weights_say_what_to_download(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    missing = "test/no-such-clip"
    with pytest.raises(
        ThgsError,
        match=f"CLIP weights for '{missing}' not found in the Hugging Face cache.*"
        f"`hf download {missing}`",
    ):
        CLIPImageEncoder(space=missing)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(
        ThgsError,
        match=rf"^{re.escape(str(empty))}: not a Hugging Face model folder \(no config\.json\)",
    ):
        CLIPImageEncoder(space=SPACE, model_path=empty)
    (empty / "config.json").write_text(json.dumps({"model_type": "clip"}))
    with pytest.raises(
        ThgsError, match=f"CLIP weights for '{SPACE}' not found in {re.escape(str(empty))}"
    ):
        CLIPImageEncoder(space=SPACE, model_path=empty)


def test_no_torchvision_or_opencv_import():
    import thgs.guidance.preprocess.clip_features as module

    tree = ast.parse(Path(module.__file__).read_text())
    imported = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for alias in node.names
    }
    imported |= {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert "torch" in imported and "thgs.errors" in imported  # the scan sees the imports
    assert not {name.split(".")[0] for name in imported if name} & {"torchvision", "cv2"}
