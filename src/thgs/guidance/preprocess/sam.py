"""Point-prompted SAM and SAM 2 through transformers (``SamModel``, ``Sam2Model``), no torchvision.

A :class:`PointSegmenter` embeds an image once (:meth:`PointSegmenter.embed`), decodes SAM's
three multimask outputs for batches of single foreground points (:meth:`PointSegmenter.decode`,
low-resolution logits and predicted IoU) and upsamples the logits of the masks worth keeping to
the image's own size (:meth:`PointSegmenter.upsample`). It reproduces the
original predictors' image handling, written here because transformers' SAM image processors
import torchvision:

- SAM (ViT-B/L/H): resize so the longer side is the model's input size (1024), each side
  ``int(side · scale + 0.5)``, bilinear (PIL, as segment-anything's ``ResizeLongestSide``);
  normalize with ImageNet's mean and std; pad bottom and right with zeros to a square. Low-res
  logits (256²) are upsampled to the padded square, cropped to the resized image and upsampled to
  the original size (bilinear, ``align_corners=False``).
- SAM 2 (Hiera): resize to the square input (1024²) without keeping the aspect ratio; normalize;
  low-res logits are upsampled straight to the original size.

Point prompts are pixel coordinates ``(x, y)`` of the original image (x = column), scaled into the
model's input frame as the original predictors do; the prompt encoder adds the half-pixel shift.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from thgs._hf import load_local_model
from thgs.errors import InputError, ThgsError

__all__ = ["DEFAULT_SAM", "EmbeddedImage", "PointSegmenter"]

logger = logging.getLogger(__name__)

DEFAULT_SAM = "facebook/sam-vit-huge"
"""The reference's mask model: SAM ViT-H, in Hugging Face format."""

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True, eq=False)
class EmbeddedImage:
    """An image after SAM's image encoder.

    Attributes:
        embeddings: the encoder's output for one image (a [1, C, h, w] tensor for SAM, a list of
            multi-scale [1, C_k, h_k, w_k] tensors for SAM 2), on the model's device.
        height, width: the original image's size in pixels.
        resized_height, resized_width: its size inside the model's input square.
    """

    embeddings: torch.Tensor | list[torch.Tensor]
    height: int
    width: int
    resized_height: int
    resized_width: int


class PointSegmenter:
    """SAM or SAM 2 (chosen by the checkpoint's ``model_type``), for point prompts.

    Args:
        model: the Hugging Face model id (default :data:`DEFAULT_SAM`, SAM ViT-H); the weights are
            read from the Hugging Face cache (``$HF_HOME``, default ``~/.cache/huggingface``) and
            never downloaded.
        model_path: a local folder with the model in Hugging Face format, instead of the cache.
        device: torch device.
        dtype: weights and activations dtype (e.g. ``torch.bfloat16`` on a GPU); default float32.

    Raises:
        ThgsError: transformers is missing, the weights are not found (the message names the model
            and where it was looked for), or the checkpoint is neither SAM nor SAM 2.
    """

    def __init__(
        self,
        model: str = DEFAULT_SAM,
        model_path: str | os.PathLike[str] | None = None,
        *,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
    ):
        try:
            from transformers import AutoConfig, Sam2Model, SamModel
        except ImportError as error:
            raise ThgsError("SAM needs transformers: pip install 'thgs[models]'") from error
        self.name = model if model_path is None else str(model_path)

        def load(source: str):
            config = AutoConfig.from_pretrained(source, local_files_only=True)
            classes = {"sam": SamModel, "sam2": Sam2Model}
            if config.model_type not in classes:
                raise ThgsError(
                    f"{self.name}: a {config.model_type!r} checkpoint, expected SAM ('sam') or "
                    "SAM 2 ('sam2')"
                )
            network = classes[config.model_type].from_pretrained(
                source, local_files_only=True, dtype=dtype
            )
            return config, network.to(device).eval()

        (config, self._model), source = load_local_model(
            load, model, model_path, what="SAM", hint="--sam DIR"
        )
        self.kind: str = config.model_type
        self.device = torch.device(device)
        self.dtype = dtype
        self.input_size = int(config.prompt_encoder_config.image_size)
        self._mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(3, 1, 1)
        self._std = torch.tensor(IMAGENET_STD, device=self.device).view(3, 1, 1)
        logger.info(
            "loaded %s (%s, %d px input) from %s on %s",
            self.kind,
            model,
            self.input_size,
            source,
            device,
        )

    def _resized_size(self, height: int, width: int) -> tuple[int, int]:
        if self.kind == "sam2":
            return self.input_size, self.input_size
        scale = self.input_size / max(height, width)
        return int(height * scale + 0.5), int(width * scale + 0.5)

    def embed(self, image: np.ndarray) -> EmbeddedImage:
        """Run the image encoder on one RGB image.

        Args:
            image: [H, W, 3] uint8 RGB.

        Raises:
            InputError: not an [H, W, 3] uint8 array.
        """
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InputError(
                "image", f"expected [H, W, 3] uint8 RGB, got {image.dtype} {list(image.shape)}"
            )
        height, width = image.shape[:2]
        resized_height, resized_width = self._resized_size(height, width)
        resized = Image.fromarray(image).resize((resized_width, resized_height), Image.BILINEAR)
        pixels = torch.from_numpy(np.array(resized)).to(self.device).permute(2, 0, 1)
        pixels = (pixels.float() / 255.0 - self._mean) / self._std
        pixels = F.pad(
            pixels, (0, self.input_size - resized_width, 0, self.input_size - resized_height)
        )
        with torch.inference_mode():
            embeddings = self._model.get_image_embeddings(pixels[None].to(self.dtype))
        return EmbeddedImage(embeddings, height, width, resized_height, resized_width)

    def decode(
        self, embedded: EmbeddedImage, points: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """SAM's three low-resolution masks for each single-point prompt.

        Args:
            embedded: the image, from :meth:`embed`.
            points: [P, 2] float (x, y) pixel coordinates in the original image.

        Returns:
            ``(low_res, iou)``: [P, 3, h, w] float32 mask logits at the decoder's resolution
            (256² for the released models; :meth:`upsample` brings them to the image) and [P, 3]
            float32 predicted IoU, both on the model's device. Output k is SAM's k-th multimask
            output (small to large, roughly).
        """
        if points.ndim != 2 or points.shape[1] != 2:
            raise InputError("points", f"expected [P, 2] (x, y), got {list(points.shape)}")
        scale = torch.tensor(
            [embedded.resized_width / embedded.width, embedded.resized_height / embedded.height],
            device=self.device,
        )
        prompts = (points.to(self.device, torch.float32) * scale)[None, :, None, :]
        labels = torch.ones(prompts.shape[:3], dtype=torch.int64, device=self.device)
        with torch.inference_mode():
            output = self._model(
                image_embeddings=embedded.embeddings,
                input_points=prompts.to(self.dtype),
                input_labels=labels,
                multimask_output=True,
            )
        return output.pred_masks[0].float(), output.iou_scores[0].float()

    def upsample(self, low_res: torch.Tensor, embedded: EmbeddedImage) -> torch.Tensor:
        """[K, h, w] low-resolution logits from :meth:`decode` → [K, H, W] float32 logits at the
        original image's size (a pixel is in the mask where its logit > 0)."""
        size = (embedded.height, embedded.width)
        low_res = low_res[:, None]
        with torch.inference_mode():
            if self.kind == "sam2":
                return F.interpolate(low_res, size, mode="bilinear", align_corners=False)[:, 0]
            square = F.interpolate(
                low_res, (self.input_size, self.input_size), mode="bilinear", align_corners=False
            )
            square = square[..., : embedded.resized_height, : embedded.resized_width]
            return F.interpolate(square, size, mode="bilinear", align_corners=False)[:, 0]
