"""Per-mask CLIP image features, computed as LangSplat computes them, batched on the device.

Each mask of a view gets one feature row: the CLIP image embedding of the mask's pixels, cut out of
the view and squared up. LangSplat's reference (``preprocess.py``) does, per mask:

1. zero every pixel outside the mask (``image[mask == 0] = 0``);
2. crop the mask's bounding box;
3. pad the crop with zeros to a square of side ``L = max(w, h)``, the crop centred: placed at
   offset ``(L − w) // 2`` horizontally, or ``(L − h) // 2`` vertically;
4. resize the square to 224 × 224 with ``cv2.resize`` (bilinear, ``INTER_LINEAR``: output pixel
   ``u`` samples source coordinate ``(u + 0.5) · L / 224 − 0.5``, clamped to ``[0, L − 1]``, with
   no antialiasing);
5. divide by 255, normalize with CLIP's mean and std (:data:`CLIP_MEAN`, :data:`CLIP_STD`);
6. encode with the CLIP image tower and L2-normalize.

:func:`mask_crops` does steps 1–4 for all masks at once on the tensors' device: it computes each
mask's sampling grid in square space, maps it to image coordinates and gathers the four bilinear
neighbours of every output pixel (image value and mask bit) straight from the full image, so no
per-mask image is ever built and memory is O(n · size²). :class:`CLIPImageEncoder` does steps 5–6
through ``transformers.CLIPModel``; :func:`mask_features` chains the two batch by batch.

Deliberate difference from the reference: boxes here are inclusive pixel corners
``(x0, y0, x1, y1)`` and the crop covers all of them, ``w = x1 − x0 + 1`` columns and
``h = y1 − y0 + 1`` rows. The reference crops SAM's XYWH box, whose ``w = x1 − x0`` comes from
inclusive corners, so it drops the mask's last column and row (a single-pixel mask gives it an
empty crop). Smaller differences: the reference resizes uint8 images and rounds the result, and
runs CLIP in float16; here pixels stay float32 and the model's dtype is a choice.

The 224 is not hard-coded: the crop side is the model's input size, ``vision_config.image_size``
(224 for ViT-B/16), exposed as :attr:`CLIPImageEncoder.image_size`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch

from thgs._hf import load_local_model
from thgs._open_clip import load_clip_model
from thgs.errors import InputError, ThgsError
from thgs.text import LANGSPLAT_SPACE, clip_space, known_dim

__all__ = [
    "CLIP_MEAN",
    "CLIP_STD",
    "CLIPImageEncoder",
    "mask_crops",
    "mask_features",
]

logger = logging.getLogger(__name__)

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
"""CLIP's per-channel (RGB) pixel mean, for pixels in [0, 1]."""

CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
"""CLIP's per-channel (RGB) pixel standard deviation, for pixels in [0, 1]."""


def _check_inputs(
    image: torch.Tensor, masks: torch.Tensor, boxes: torch.Tensor, *, same_device: bool
) -> None:
    """Shapes, dtypes, devices and box ranges of :func:`mask_crops`' inputs, or InputError."""
    for name, value in (("image", image), ("masks", masks), ("boxes", boxes)):
        if not isinstance(value, torch.Tensor):
            raise InputError(name, f"expected a torch.Tensor, got {type(value).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError("image", f"expected shape [H, W, 3], got {list(image.shape)}")
    if not image.is_floating_point():
        raise InputError(
            "image",
            f"expected floating-point values in [0, 1], got {image.dtype} "
            "(divide 8-bit images by 255)",
        )
    height, width = image.shape[:2]
    if masks.ndim != 3 or tuple(masks.shape[1:]) != (height, width):
        raise InputError(
            "masks",
            f"expected shape [n, {height}, {width}] (the image is {list(image.shape)}), "
            f"got {list(masks.shape)}",
        )
    if masks.dtype != torch.bool:
        raise InputError("masks", f"expected dtype torch.bool, got {masks.dtype}")
    n = masks.shape[0]
    if boxes.ndim != 2 or tuple(boxes.shape) != (n, 4):
        raise InputError(
            "boxes",
            f"expected shape [{n}, 4] (one (x0, y0, x1, y1) per mask; masks are "
            f"{list(masks.shape)}), got {list(boxes.shape)}",
        )
    if boxes.is_floating_point() or boxes.is_complex() or boxes.dtype == torch.bool:
        raise InputError("boxes", f"expected integer pixel corners, got dtype {boxes.dtype}")
    if same_device and not (image.device == masks.device == boxes.device):
        raise InputError(
            "mask_crops",
            f"image, masks and boxes must be on one device, got {image.device}, "
            f"{masks.device} and {boxes.device}",
        )
    if n:
        x0, y0, x1, y1 = boxes.unbind(1)
        bad = (x0 < 0) | (y0 < 0) | (x1 < x0) | (y1 < y0) | (x1 >= width) | (y1 >= height)
        if bool(bad.any()):
            index = int(bad.nonzero()[0, 0])
            raise InputError(
                "boxes",
                f"box {index} is {boxes[index].tolist()}; boxes are inclusive pixel corners "
                f"(x0, y0, x1, y1) with 0 ≤ x0 ≤ x1 < {width} and 0 ≤ y0 ≤ y1 < {height} "
                f"(image {list(image.shape)})",
            )


def _axis_samples(
    start: torch.Tensor, stop: torch.Tensor, side: torch.Tensor, size: int, limit: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One axis of the bilinear sampling grid of every mask.

    The crop spans pixels ``start … stop`` (inclusive) on this axis and sits centred in a square of
    side ``L``; output pixel ``u`` samples square coordinate ``s = (u + 0.5) · L / size − 0.5``,
    clamped to ``[0, L − 1]`` (cv2's ``INTER_LINEAR``). ``s`` is split into its integer part and
    fraction in exact integer arithmetic, so no float rounding moves a sample across a pixel.

    Args:
        start, stop: [n] int64 inclusive crop extent on this axis, in image pixels.
        side: [n] int64 the square's side ``L = max(w, h)``.
        size: output side.
        limit: the image's extent on this axis (W or H), to keep gather indices in range.

    Returns:
        ``(index0, index1, weight0, weight1)``, each [n, size]: the image coordinates of the two
        neighbours (clamped into the image) and their float32 weights, zero for a neighbour in the
        square's padding.
    """
    extent = stop - start + 1  # [n] w or h
    origin = start - (side - extent) // 2  # image coordinate of the square's first pixel
    u = torch.arange(size, device=start.device, dtype=torch.int64)
    # s = numerator / denominator exactly: ((2u + 1) · L − size) / (2 · size)
    numerator = (2 * u + 1)[None, :] * side[:, None] - size  # [n, size]
    denominator = 2 * size
    index0 = torch.div(numerator, denominator, rounding_mode="floor")
    fraction = (numerator - index0 * denominator).to(torch.float32) / denominator
    low = numerator < 0  # s < 0: clamp to the first pixel
    high = index0 >= (side - 1)[:, None]  # s ≥ L − 1: clamp to the last pixel
    index0 = torch.where(low, 0, torch.minimum(index0, (side - 1)[:, None]))
    fraction = torch.where(low | high, 0.0, fraction)
    index1 = torch.minimum(index0 + 1, (side - 1)[:, None])
    weights = []
    indices = []
    for index, weight in ((index0, 1.0 - fraction), (index1, fraction)):
        pixel = origin[:, None] + index  # image coordinate; outside the crop = padding
        inside = (pixel >= start[:, None]) & (pixel <= stop[:, None])
        weights.append(torch.where(inside, weight, 0.0))
        indices.append(pixel.clamp(0, limit - 1))
    return indices[0], indices[1], weights[0], weights[1]


def mask_crops(
    image: torch.Tensor, masks: torch.Tensor, boxes: torch.Tensor, size: int = 224
) -> torch.Tensor:
    """Cut out every mask, square it up with zeros and resize it to ``size`` × ``size``.

    Steps 1–4 of the reference (module docstring) for all masks at once, on the tensors' device:
    the image is zeroed outside the mask, cropped to the mask's box (inclusive corners, all of it),
    padded with zeros to a centred square of side ``L = max(w, h)`` and resized bilinearly like
    ``cv2.resize(..., interpolation=INTER_LINEAR)``. Each output pixel reads its four bilinear
    neighbours (image value times mask bit; zero in the padding) directly from the full image, so
    memory is O(n · size²) beyond the inputs.

    Args:
        image: [H, W, 3] floating-point RGB in [0, 1] (computed in float32).
        masks: [n, H, W] bool.
        boxes: [n, 4] integer inclusive pixel corners ``(x0, y0, x1, y1)`` per mask, normally the
            mask's bounding box (pixels of the mask outside its box are left out, as in the
            reference).
        size: output side in pixels (the CLIP model's input size, 224 for ViT-B/16).

    Returns:
        [n, 3, size, size] float32 in [0, 1], on the inputs' device.

    Raises:
        InputError: a wrong shape, dtype or device, or a box outside the image or inverted.
    """
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise InputError("size", f"expected a positive int, got {size!r}")
    _check_inputs(image, masks, boxes, same_device=True)
    n = masks.shape[0]
    height, width = image.shape[:2]
    if n == 0:
        return torch.zeros((0, 3, size, size), dtype=torch.float32, device=image.device)
    boxes = boxes.to(torch.int64)
    x0, y0, x1, y1 = boxes.unbind(1)
    side = torch.maximum(x1 - x0 + 1, y1 - y0 + 1)  # [n] L
    xs = _axis_samples(x0, x1, side, size, width)
    ys = _axis_samples(y0, y1, side, size, height)
    pixels = image.to(torch.float32).reshape(height * width, 3)
    flat_masks = masks.reshape(n, height * width)
    crops = torch.zeros((n, size, size, 3), dtype=torch.float32, device=image.device)
    for row, row_weight in ((ys[0], ys[2]), (ys[1], ys[3])):
        for column, column_weight in ((xs[0], xs[2]), (xs[1], xs[3])):
            flat = (row[:, :, None] * width + column[:, None, :]).reshape(n, size * size)
            inside = torch.gather(flat_masks, 1, flat).reshape(n, size, size)
            weight = row_weight[:, :, None] * column_weight[:, None, :] * inside
            crops += weight[..., None] * pixels[flat].reshape(n, size, size, 3)
    return crops.permute(0, 3, 1, 2).contiguous()


class CLIPImageEncoder:
    """The image tower of a CLIP model through ``transformers.CLIPModel``.

    An image's embedding is the model's projected image feature, L2-normalized. Loading mirrors
    :class:`thgs.text.CLIPTextEncoder`: a local folder or the Hugging Face cache, never a download.

    Args:
        space: the embedding space, i.e. the Hugging Face model id. Without ``model_path`` the
            weights are read from the Hugging Face cache (``$HF_HOME``, default
            ``~/.cache/huggingface``; nothing is ever downloaded) and the default is
            :data:`thgs.text.LANGSPLAT_SPACE`; with it, the default is the folder's own space
            (:func:`thgs.text.clip_space`: its Hugging Face id where that can be told, else the
            folder's absolute path).
        model_path: a local folder holding the model in Hugging Face format (``config.json``,
            weights), instead of the cache.
        device: torch device for the model.
        dtype: the model's dtype, e.g. ``torch.float16`` on CUDA (the reference runs CLIP in
            float16); default the stored one. Features are returned as float32 either way.

    Attributes:
        space: the embedding space (model id, or a local folder's absolute path).
        model_path: the local folder the model was read from (absolute), or None (the cache).
        dim: D, the projection dimension (512 for ViT-B/16).
        image_size: the model's input side in pixels (224 for ViT-B/16).
        device: the model's torch device.

    Raises:
        ThgsError: transformers is missing, or the weights are not found (the message names the
            model to download and where to put it).
        InputError: the model's projection dimension is not the one of ``space`` where thgs
            knows it (:func:`thgs.text.known_dim`).
    """

    def __init__(
        self,
        space: str | None = None,
        model_path: str | os.PathLike[str] | None = None,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | None = None,
    ):
        try:
            import transformers  # noqa: F401  (the dependency this encoder needs)
        except ImportError as error:
            raise ThgsError(
                "the CLIP image encoder needs transformers: pip install 'thgs[models]'"
            ) from error
        if space is None:
            space = LANGSPLAT_SPACE if model_path is None else clip_space(model_path)
        self.space = space
        self.model_path = None if model_path is None else Path(model_path).expanduser().resolve()
        self._model, source = load_local_model(
            lambda source: load_clip_model(source).to(device).eval(),
            space,
            model_path,
            what="CLIP",
            hint="--clip DIR",
        )
        if dtype is not None:
            self._model.to(dtype)
        self.device = torch.device(device)
        self.dim = int(self._model.config.projection_dim)
        expected = known_dim(space)
        if expected is not None and self.dim != expected:
            raise InputError(
                source,
                f"projects to {self.dim}-D but {space} is {expected}-D: not that model; name the "
                "features' space with --space, or leave it out to use the folder's own",
            )
        self.image_size = int(self._model.config.vision_config.image_size)
        self._dtype = next(self._model.parameters()).dtype
        self._mean = torch.tensor(CLIP_MEAN, device=self.device).reshape(1, 3, 1, 1)
        self._std = torch.tensor(CLIP_STD, device=self.device).reshape(1, 3, 1, 1)
        logger.info(
            "loaded image encoder %s (%d-D, %d px, %s) from %s",
            self.space,
            self.dim,
            self.image_size,
            self._dtype,
            source,
        )

    def encode(self, pixels: torch.Tensor) -> torch.Tensor:
        """Embed images already at the model's input size.

        Args:
            pixels: [n, 3, S, S] floating-point RGB in [0, 1], S = :attr:`image_size`; any
                device (moved to the model's).

        Returns:
            [n, D] float32 unit rows on the model's device.

        Raises:
            InputError: a wrong shape or dtype.
        """
        size = self.image_size
        if not isinstance(pixels, torch.Tensor):
            raise InputError("pixels", f"expected a torch.Tensor, got {type(pixels).__name__}")
        if pixels.ndim != 4 or tuple(pixels.shape[1:]) != (3, size, size):
            raise InputError(
                "pixels",
                f"expected shape [n, 3, {size}, {size}] (the model's input size is {size}), "
                f"got {list(pixels.shape)}",
            )
        if not pixels.is_floating_point():
            raise InputError(
                "pixels", f"expected floating-point values in [0, 1], got {pixels.dtype}"
            )
        if pixels.shape[0] == 0:
            return torch.zeros((0, self.dim), dtype=torch.float32, device=self.device)
        normalized = (pixels.to(self.device, torch.float32) - self._mean) / self._std
        with torch.inference_mode():
            output = self._model.get_image_features(pixel_values=normalized.to(self._dtype))
        # transformers ≥ 5 returns the projected features as pooler_output, 4.x a tensor
        features = output if isinstance(output, torch.Tensor) else output.pooler_output
        features = features.to(torch.float32)
        return features / torch.linalg.vector_norm(features, dim=1, keepdim=True)


def mask_features(
    encoder: CLIPImageEncoder,
    image: torch.Tensor,
    masks: torch.Tensor,
    boxes: torch.Tensor,
    batch_size: int = 64,
) -> np.ndarray:
    """One CLIP feature row per mask: :func:`mask_crops` then :meth:`CLIPImageEncoder.encode`.

    Masks are cropped and encoded ``batch_size`` at a time on the encoder's device (the image is
    moved there once, the masks and boxes batch by batch), so memory stays bounded however many
    masks a view has. Results do not depend on ``batch_size``.

    Args:
        encoder: the CLIP image tower; crops are made at its :attr:`~CLIPImageEncoder.image_size`.
        image: [H, W, 3] floating-point RGB in [0, 1].
        masks: [n, H, W] bool.
        boxes: [n, 4] integer inclusive pixel corners ``(x0, y0, x1, y1)`` per mask.
        batch_size: masks per forward pass.

    Returns:
        [n, D] float32 unit rows, in mask order; [0, D] for no masks.

    Raises:
        InputError: a wrong shape, dtype or box (see :func:`mask_crops`), or batch size.
    """
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise InputError("batch_size", f"expected a positive int, got {batch_size!r}")
    _check_inputs(image, masks, boxes, same_device=False)
    n = masks.shape[0]
    device = encoder.device
    image = image.to(device)
    rows = [np.zeros((0, encoder.dim), dtype=np.float32)]
    for start in range(0, n, batch_size):
        stop = min(start + batch_size, n)
        crops = mask_crops(
            image,
            masks[start:stop].to(device),
            boxes[start:stop].to(device),
            size=encoder.image_size,
        )
        rows.append(encoder.encode(crops).cpu().numpy())
    logger.debug("encoded %d masks of a %s image", n, list(image.shape))
    return np.concatenate(rows)
