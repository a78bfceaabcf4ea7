"""Randomly initialised, small models of the real architectures, saved in Hugging Face format like
downloaded weights: CLIP (text and vision towers), SAM (ViT) and SAM 2 (Hiera). No weights can be
downloaded here; these exercise the real loading and inference code."""

from __future__ import annotations

import string
from pathlib import Path

import torch
import transformers


def tiny_clip(folder: Path, *, image_size: int = 32) -> Path:
    """A CLIP with 32-wide towers (2 text layers, 1 vision layer), a 16-D projection, vision input
    ``image_size`` px, and a character-level BPE tokenizer."""
    letters = list(string.ascii_lowercase)
    vocab = {c: i for i, c in enumerate(letters)}
    vocab |= {c + "</w>": len(letters) + i for i, c in enumerate(letters)}
    vocab |= {"<|startoftext|>": len(vocab), "<|endoftext|>": len(vocab) + 1}
    tokenizer = transformers.CLIPTokenizer(vocab=vocab, merges=[])
    config = transformers.CLIPConfig(
        text_config={
            "vocab_size": len(vocab),
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "max_position_embeddings": 77,
            "bos_token_id": vocab["<|startoftext|>"],
            "eos_token_id": vocab["<|endoftext|>"],
            "pad_token_id": vocab["<|endoftext|>"],
        },
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": image_size,
            "patch_size": 16,
        },
        projection_dim=16,
    )
    torch.manual_seed(0)
    model = transformers.CLIPModel(config).eval()
    model.save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return folder


def _decoder_and_prompts(image_size: int) -> dict:
    return {
        "prompt_encoder_config": {
            "hidden_size": 32,
            "image_size": image_size,
            "patch_size": 16,
            "mask_input_channels": 4,
        },
        "mask_decoder_config": {
            "hidden_size": 32,
            "mlp_dim": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 32,
        },
    }


def _spread_weights(model: torch.nn.Module, seed: int) -> None:
    """Random weights with a spread large enough that masks and scores vary (SAM's own init is
    near zero in the vision tower, which makes every logit about 0)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * 0.2)


def tiny_sam(folder: Path, *, image_size: int = 256, seed: int = 0) -> Path:
    """A SAM (ViT) with a 2-layer 32-wide image encoder at ``image_size`` px input."""
    config = transformers.SamConfig(
        vision_config={
            "hidden_size": 32,
            "output_channels": 32,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": image_size,
            "patch_size": 16,
            "window_size": 4,
            "global_attn_indexes": [1],
            "num_pos_feats": 16,
            "mlp_dim": 64,
        },
        **_decoder_and_prompts(image_size),
    )
    model = transformers.SamModel(config).eval()
    _spread_weights(model, seed)
    model.save_pretrained(folder)
    return folder


def tiny_sam2(folder: Path, *, image_size: int = 256, seed: int = 0) -> Path:
    """A SAM 2 with a 5-block Hiera image encoder (8–64 wide) at ``image_size`` px input."""
    dims = [8, 16, 32, 64]
    side = image_size // 4
    config = transformers.Sam2Config(
        vision_config={
            "backbone_config": {
                "model_type": "sam2_hiera_det_model",
                "hidden_size": dims[0],
                "image_size": [image_size, image_size],
                "blocks_per_stage": [1, 1, 2, 1],
                "embed_dim_per_stage": dims,
                "num_attention_heads_per_stage": [1, 1, 1, 1],
                "window_size_per_stage": [4, 4, 4, 4],
                "global_attention_blocks": [3],
                "window_positional_embedding_background_size": [2, 2],
            },
            "backbone_channel_list": dims[::-1],
            "backbone_feature_sizes": [[side, side], [side // 2, side // 2], [side // 4] * 2],
            "fpn_hidden_size": 32,
        },
        **_decoder_and_prompts(image_size),
    )
    model = transformers.Sam2Model(config).eval()
    _spread_weights(model, seed)
    model.save_pretrained(folder)
    return folder
