"""Read CLIP checkpoints published in OpenCLIP's format as ``transformers.CLIPModel``.

LangSplat's model, OpenCLIP ViT-B/16 ``laion2b_s34b_b88k``, is published on the Hugging Face Hub
as ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K`` with OpenCLIP's files only
(``open_clip_config.json``, ``open_clip_model.safetensors`` or ``open_clip_pytorch_model.bin``,
and the tokenizer) and no ``config.json``, so ``CLIPModel.from_pretrained`` cannot read it. The
OpenCLIP package itself imports torchvision, which thgs does not install. This module builds the
equivalent ``CLIPConfig`` from ``open_clip_config.json`` and renames the weights (OpenCLIP's
packed attention projection split into query, key and value; its ``[width, D]`` projections
transposed): the same network, the same features.

Only OpenCLIP's plain ViT CLIP is read (class-token pooling, pre-norm blocks, no layer scale,
no attentional pooler, tied widths of 64 per head in the vision tower); anything else is refused
with the key or setting that is not supported.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import torch

from thgs._torch_load import load_tensors
from thgs.errors import InputError

__all__ = [
    "OPEN_CLIP_CONFIG",
    "is_open_clip_folder",
    "load_clip_model",
    "load_clip_tokenizer",
    "model_folder",
    "open_clip_config",
    "open_clip_state_dict",
]

logger = logging.getLogger(__name__)

OPEN_CLIP_CONFIG = "open_clip_config.json"
"""The file that marks a folder as an OpenCLIP checkpoint."""

_WEIGHTS = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")
_HEAD_WIDTH = 64  # OpenCLIP's vision tower: heads = width // 64
_TOWER_KEYS = {
    "ln_1.weight": "layer_norm1.weight",
    "ln_1.bias": "layer_norm1.bias",
    "ln_2.weight": "layer_norm2.weight",
    "ln_2.bias": "layer_norm2.bias",
    "attn.out_proj.weight": "self_attn.out_proj.weight",
    "attn.out_proj.bias": "self_attn.out_proj.bias",
    "mlp.c_fc.weight": "mlp.fc1.weight",
    "mlp.c_fc.bias": "mlp.fc1.bias",
    "mlp.c_proj.weight": "mlp.fc2.weight",
    "mlp.c_proj.bias": "mlp.fc2.bias",
}


def model_folder(source: str | os.PathLike[str]) -> Path | None:
    """The folder a model source names: an existing folder, or a model id's snapshot in the
    Hugging Face cache (never downloaded); None when neither exists."""
    path = Path(source).expanduser()
    if path.is_dir():
        return path
    try:
        from huggingface_hub import snapshot_download
        from huggingface_hub.errors import LocalEntryNotFoundError
    except ImportError:  # pragma: no cover - transformers depends on huggingface_hub
        return None
    try:
        return Path(snapshot_download(str(source), local_files_only=True))
    except (LocalEntryNotFoundError, ValueError, OSError):
        return None


def is_open_clip_folder(folder: str | os.PathLike[str]) -> bool:
    """Whether ``folder`` holds an OpenCLIP checkpoint and no ``transformers`` config."""
    folder = Path(folder)
    return (folder / OPEN_CLIP_CONFIG).is_file() and not (folder / "config.json").is_file()


def _positive_int(value: Any, path: Path, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise InputError(path, f"{name} must be a positive integer, got {value!r}")
    return value


def open_clip_config(folder: str | os.PathLike[str]):
    """The ``transformers.CLIPConfig`` of the OpenCLIP checkpoint in ``folder``.

    Raises:
        InputError: ``open_clip_config.json`` is unreadable, lacks a size, or describes a model
            this reader does not support (a non-ViT tower, layer scale, another pooling, …).
    """
    from transformers import CLIPConfig

    path = Path(folder) / OPEN_CLIP_CONFIG
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(path, f"not readable JSON ({error})") from error
    model = document.get("model_cfg") if isinstance(document, dict) else None
    if not isinstance(model, dict):
        raise InputError(path, "has no 'model_cfg' object")
    vision, text = model.get("vision_cfg"), model.get("text_cfg")
    if not isinstance(vision, dict) or not isinstance(text, dict):
        raise InputError(path, "model_cfg needs 'vision_cfg' and 'text_cfg' objects")
    unsupported = {
        "vision_cfg": {
            key: vision[key]
            for key in ("timm_model_name", "ls_init_value", "attentional_pool", "no_ln_pre")
            if vision.get(key)
        },
        "text_cfg": {
            key: text[key]
            for key in ("hf_model_name", "ls_init_value", "no_causal_mask", "proj_bias")
            if text.get(key)
        },
    }
    if vision.get("pool_type", "tok") != "tok":
        unsupported["vision_cfg"]["pool_type"] = vision["pool_type"]
    if text.get("pool_type", "argmax") not in ("argmax", "eos"):
        unsupported["text_cfg"]["pool_type"] = text["pool_type"]
    if vision.get("head_width", _HEAD_WIDTH) != _HEAD_WIDTH:
        unsupported["vision_cfg"]["head_width"] = vision["head_width"]
    for tower, settings in unsupported.items():
        if settings:
            name, value = next(iter(settings.items()))
            raise InputError(
                path, f"{tower}.{name} = {value!r} is not supported (plain ViT CLIP only)"
            )
    act = "quick_gelu" if model.get("quick_gelu") else "gelu"
    vision_width = _positive_int(vision.get("width"), path, "vision_cfg.width")
    text_width = _positive_int(text.get("width"), path, "text_cfg.width")
    vocab_size = _positive_int(text.get("vocab_size", 49408), path, "vocab_size")
    return CLIPConfig(
        projection_dim=_positive_int(model.get("embed_dim"), path, "embed_dim"),
        text_config={
            "vocab_size": vocab_size,
            # OpenCLIP's start and end tokens are the vocabulary's last two; it pools at the end
            # token (the largest id), where transformers pools at the first eos_token_id
            "bos_token_id": vocab_size - 2,
            "eos_token_id": vocab_size - 1,
            "pad_token_id": 0,
            "hidden_size": text_width,
            "intermediate_size": int(text_width * text.get("mlp_ratio", 4.0)),
            "num_hidden_layers": _positive_int(text.get("layers"), path, "text_cfg.layers"),
            "num_attention_heads": _positive_int(text.get("heads", 8), path, "text_cfg.heads"),
            "max_position_embeddings": _positive_int(
                text.get("context_length", 77), path, "context_length"
            ),
            "hidden_act": act,
            "layer_norm_eps": 1e-5,
        },
        vision_config={
            "hidden_size": vision_width,
            "intermediate_size": int(vision_width * vision.get("mlp_ratio", 4.0)),
            "num_hidden_layers": _positive_int(vision.get("layers"), path, "vision_cfg.layers"),
            "num_attention_heads": vision_width // _HEAD_WIDTH,
            "image_size": _positive_int(vision.get("image_size"), path, "image_size"),
            "patch_size": _positive_int(vision.get("patch_size"), path, "patch_size"),
            "hidden_act": act,
            "layer_norm_eps": 1e-5,
        },
    )


def _read_weights(folder: Path) -> tuple[dict[str, torch.Tensor], Path]:
    for name in _WEIGHTS:
        path = folder / name
        if not path.is_file():
            continue
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            try:
                return load_file(str(path)), path
            except Exception as error:  # safetensors raises several kinds on damaged files
                raise InputError(path, f"not a readable checkpoint ({error})") from error
        weights = load_tensors(path, "checkpoint")
        if isinstance(weights, dict) and isinstance(weights.get("state_dict"), dict):
            weights = weights["state_dict"]
        if not isinstance(weights, dict):
            raise InputError(path, "holds no state dict")
        return {key.removeprefix("module."): value for key, value in weights.items()}, path
    raise InputError(folder, f"an OpenCLIP folder without weights ({' or '.join(_WEIGHTS)})")


def _blocks(weights: dict[str, torch.Tensor], source: str, target: str, layers: int) -> dict:
    renamed = {}
    for i in range(layers):
        prefix, out = f"{source}.resblocks.{i}.", f"{target}.layers.{i}."
        for key, new in _TOWER_KEYS.items():
            renamed[out + new] = weights.pop(prefix + key)
        q, k, v = weights.pop(prefix + "attn.in_proj_weight").chunk(3, dim=0)
        qb, kb, vb = weights.pop(prefix + "attn.in_proj_bias").chunk(3, dim=0)
        for name, weight, bias in (("q", q, qb), ("k", k, kb), ("v", v, vb)):
            renamed[f"{out}self_attn.{name}_proj.weight"] = weight
            renamed[f"{out}self_attn.{name}_proj.bias"] = bias
    return renamed


def open_clip_state_dict(
    weights: dict[str, torch.Tensor], config, path: str | os.PathLike[str] = "weights"
) -> dict[str, torch.Tensor]:
    """OpenCLIP's state dict renamed to ``transformers.CLIPModel``'s.

    Args:
        weights: OpenCLIP's parameters (``visual.*``, ``transformer.*``, ``token_embedding``,
            ``positional_embedding``, ``ln_final``, ``text_projection`` [width, D],
            ``logit_scale``; ``visual.proj`` [width, D]).
        config: the model's ``CLIPConfig`` (:func:`open_clip_config`).
        path: the file, for messages.

    Raises:
        InputError: a parameter is missing, or one is left over that the plain ViT CLIP does not
            have (the message names it).
    """
    weights = dict(weights)
    weights.pop("attn_mask", None)  # a buffer some OpenCLIP versions save
    try:
        renamed = {
            "logit_scale": weights.pop("logit_scale"),
            "text_model.embeddings.token_embedding.weight": weights.pop("token_embedding.weight"),
            "text_model.embeddings.position_embedding.weight": weights.pop("positional_embedding"),
            "text_model.final_layer_norm.weight": weights.pop("ln_final.weight"),
            "text_model.final_layer_norm.bias": weights.pop("ln_final.bias"),
            "text_projection.weight": weights.pop("text_projection").T.contiguous(),
            "vision_model.embeddings.class_embedding": weights.pop("visual.class_embedding"),
            "vision_model.embeddings.patch_embedding.weight": weights.pop("visual.conv1.weight"),
            "vision_model.embeddings.position_embedding.weight": weights.pop(
                "visual.positional_embedding"
            ),
            "vision_model.pre_layrnorm.weight": weights.pop("visual.ln_pre.weight"),
            "vision_model.pre_layrnorm.bias": weights.pop("visual.ln_pre.bias"),
            "vision_model.post_layernorm.weight": weights.pop("visual.ln_post.weight"),
            "vision_model.post_layernorm.bias": weights.pop("visual.ln_post.bias"),
            "visual_projection.weight": weights.pop("visual.proj").T.contiguous(),
        }
        renamed |= _blocks(
            weights, "transformer", "text_model.encoder", config.text_config.num_hidden_layers
        )
        renamed |= _blocks(
            weights,
            "visual.transformer",
            "vision_model.encoder",
            config.vision_config.num_hidden_layers,
        )
    except KeyError as error:
        raise InputError(path, f"has no parameter {error.args[0]!r}") from error
    if weights:
        raise InputError(
            path, f"has parameters a plain ViT CLIP does not: {', '.join(sorted(weights)[:3])}"
        )
    return renamed


def _from_open_clip(folder: Path):
    from transformers import CLIPModel

    config = open_clip_config(folder)
    weights, path = _read_weights(folder)
    model = CLIPModel(config)
    renamed = open_clip_state_dict(weights, config, path)
    expected = model.state_dict()
    for key, value in renamed.items():
        if tuple(value.shape) != tuple(expected[key].shape):
            raise InputError(
                path,
                f"{key}: shape {list(value.shape)} but {OPEN_CLIP_CONFIG} makes it "
                f"{list(expected[key].shape)}",
            )
    model.load_state_dict(renamed, strict=False)
    missing = set(expected) - set(renamed) - {name for name, _ in model.named_buffers()}
    if missing:  # pragma: no cover - the renaming covers every parameter of CLIPModel
        raise InputError(path, f"no value for {sorted(missing)[0]}")
    logger.info("read OpenCLIP checkpoint %s as transformers CLIPModel", path)
    return model


def load_clip_model(source: str, *, dtype: torch.dtype | None = None):
    """``transformers.CLIPModel`` from a local folder or a model id in the Hugging Face cache,
    in ``transformers``' format or OpenCLIP's (never downloaded).

    Raises:
        OSError: the model is not found (as ``CLIPModel.from_pretrained`` raises it).
        InputError: an OpenCLIP checkpoint that cannot be read (:func:`open_clip_config`).
    """
    from transformers import CLIPModel

    folder = model_folder(source)
    if folder is not None and is_open_clip_folder(folder):
        model = _from_open_clip(folder)
        return model if dtype is None else model.to(dtype)
    kwargs = {} if dtype is None else {"dtype": dtype}
    return CLIPModel.from_pretrained(source, local_files_only=True, **kwargs)


def load_clip_tokenizer(source: str):
    """The tokenizer of a CLIP model from a local folder or the Hugging Face cache; an OpenCLIP
    folder's is read as ``CLIPTokenizerFast`` (OpenCLIP's BPE is CLIP's).

    Raises:
        OSError: the model is not found.
        InputError: an OpenCLIP folder without tokenizer files.
    """
    from transformers import AutoTokenizer, CLIPTokenizer, CLIPTokenizerFast

    folder = model_folder(source)
    if folder is None or not is_open_clip_folder(folder):
        return AutoTokenizer.from_pretrained(source, local_files_only=True)
    if (folder / "tokenizer.json").is_file():
        return CLIPTokenizerFast.from_pretrained(str(folder), local_files_only=True)
    if (folder / "vocab.json").is_file() and (folder / "merges.txt").is_file():
        return CLIPTokenizer.from_pretrained(str(folder), local_files_only=True)
    raise InputError(
        folder,
        "an OpenCLIP folder without tokenizer files (tokenizer.json, or vocab.json and merges.txt)",
    )
