"""OpenCLIP checkpoints (LangSplat's CLIP as the Hub publishes it: open_clip_config.json,
open_clip_model.safetensors, tokenizer, no config.json) read as transformers' CLIPModel: the
features equal those of OpenCLIP's forward pass, written out here from its definition (packed
attention projection, class-token pooling, end-of-text pooling, [width, D] projections)."""

from __future__ import annotations

import json
import math
import shutil
import string
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from thgs import InputError
from thgs.errors import ThgsError
from thgs.guidance.preprocess import CLIPImageEncoder
from thgs.text import LANGSPLAT_SPACE, CLIPTextEncoder, clip_space

transformers = pytest.importorskip("transformers")

# OpenAI's normalization, which OpenCLIP's preprocess_cfg of the LAION models repeats
MEAN = torch.tensor([0.48145466, 0.4578275, 0.40821073]).reshape(1, 3, 1, 1)
STD = torch.tensor([0.26862954, 0.26130258, 0.27577711]).reshape(1, 3, 1, 1)

VISION = {"image_size": 32, "layers": 2, "width": 64, "patch_size": 16}
TEXT = {"context_length": 77, "width": 32, "heads": 2, "layers": 2}
EMBED = 16


def _tokenizer():
    letters = list(string.ascii_lowercase)
    vocab = {c: i for i, c in enumerate(letters)}
    vocab |= {c + "</w>": len(letters) + i for i, c in enumerate(letters)}
    vocab |= {"<|startoftext|>": len(vocab), "<|endoftext|>": len(vocab) + 1}
    return transformers.CLIPTokenizer(vocab=vocab, merges=[])


def _block(prefix: str, width: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    def randn(*shape: int, scale: float = 0.2) -> torch.Tensor:
        return torch.randn(*shape, generator=generator) * scale

    return {
        f"{prefix}ln_1.weight": 1 + randn(width, scale=0.1),
        f"{prefix}ln_1.bias": randn(width, scale=0.1),
        f"{prefix}attn.in_proj_weight": randn(3 * width, width),
        f"{prefix}attn.in_proj_bias": randn(3 * width),
        f"{prefix}attn.out_proj.weight": randn(width, width),
        f"{prefix}attn.out_proj.bias": randn(width),
        f"{prefix}ln_2.weight": 1 + randn(width, scale=0.1),
        f"{prefix}ln_2.bias": randn(width, scale=0.1),
        f"{prefix}mlp.c_fc.weight": randn(4 * width, width),
        f"{prefix}mlp.c_fc.bias": randn(4 * width),
        f"{prefix}mlp.c_proj.weight": randn(width, 4 * width),
        f"{prefix}mlp.c_proj.bias": randn(width),
    }


def open_clip_weights(vocab_size: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random parameters under OpenCLIP's names and shapes (CLIP with a ViT tower)."""
    g = torch.Generator().manual_seed(seed)
    vw, tw = VISION["width"], TEXT["width"]
    tokens = (VISION["image_size"] // VISION["patch_size"]) ** 2 + 1
    weights = {
        "token_embedding.weight": torch.randn(vocab_size, tw, generator=g) * 0.5,
        "positional_embedding": torch.randn(TEXT["context_length"], tw, generator=g) * 0.1,
        "ln_final.weight": 1 + torch.randn(tw, generator=g) * 0.1,
        "ln_final.bias": torch.randn(tw, generator=g) * 0.1,
        "text_projection": torch.randn(tw, EMBED, generator=g) * 0.3,
        "logit_scale": torch.tensor(math.log(1 / 0.07)),
        "visual.class_embedding": torch.randn(vw, generator=g) * 0.5,
        "visual.positional_embedding": torch.randn(tokens, vw, generator=g) * 0.1,
        "visual.conv1.weight": torch.randn(vw, 3, 16, 16, generator=g) * 0.05,
        "visual.ln_pre.weight": 1 + torch.randn(vw, generator=g) * 0.1,
        "visual.ln_pre.bias": torch.randn(vw, generator=g) * 0.1,
        "visual.ln_post.weight": 1 + torch.randn(vw, generator=g) * 0.1,
        "visual.ln_post.bias": torch.randn(vw, generator=g) * 0.1,
        "visual.proj": torch.randn(vw, EMBED, generator=g) * 0.3,
    }
    for i in range(TEXT["layers"]):
        weights |= _block(f"transformer.resblocks.{i}.", tw, g)
    for i in range(VISION["layers"]):
        weights |= _block(f"visual.transformer.resblocks.{i}.", vw, g)
    return weights


def write_open_clip(folder: Path, *, weights=None, config=None, tokenizer: bool = True) -> Path:
    """A folder as the Hub's OpenCLIP repositories are laid out."""
    folder.mkdir(parents=True, exist_ok=True)
    tok = _tokenizer()
    if tokenizer:
        tok.save_pretrained(folder)
    model_cfg = {
        "embed_dim": EMBED,
        "vision_cfg": VISION,
        "text_cfg": TEXT | {"vocab_size": len(tok)},
    }
    document = (
        config
        if config is not None
        else {
            "model_cfg": model_cfg,
            "preprocess_cfg": {"mean": MEAN.flatten().tolist(), "std": STD.flatten().tolist()},
        }
    )
    (folder / "open_clip_config.json").write_text(json.dumps(document))
    weights = weights if weights is not None else open_clip_weights(len(tok))
    save_file(
        {k: v.contiguous() for k, v in weights.items()}, folder / "open_clip_model.safetensors"
    )
    return folder


# --- OpenCLIP's forward pass, from its definition --------------------------------------------


def _resblock(x: torch.Tensor, p: dict, prefix: str, heads: int, mask) -> torch.Tensor:
    n, length, width = x.shape
    h = F.layer_norm(x, (width,), p[prefix + "ln_1.weight"], p[prefix + "ln_1.bias"], 1e-5)
    qkv = h @ p[prefix + "attn.in_proj_weight"].T + p[prefix + "attn.in_proj_bias"]
    q, k, v = (
        t.reshape(n, length, heads, width // heads).transpose(1, 2) for t in qkv.chunk(3, -1)
    )
    scores = q @ k.transpose(-1, -2) / math.sqrt(width // heads)
    if mask is not None:
        scores = scores + mask
    attended = (scores.softmax(-1) @ v).transpose(1, 2).reshape(n, length, width)
    x = x + attended @ p[prefix + "attn.out_proj.weight"].T + p[prefix + "attn.out_proj.bias"]
    h = F.layer_norm(x, (width,), p[prefix + "ln_2.weight"], p[prefix + "ln_2.bias"], 1e-5)
    h = F.gelu(h @ p[prefix + "mlp.c_fc.weight"].T + p[prefix + "mlp.c_fc.bias"])
    return x + h @ p[prefix + "mlp.c_proj.weight"].T + p[prefix + "mlp.c_proj.bias"]


def open_clip_text(p: dict, ids: torch.Tensor) -> torch.Tensor:
    """ids [n, 77] padded with 0 after the end-of-text token, as OpenCLIP's tokenizer pads."""
    length = ids.shape[1]
    x = p["token_embedding.weight"][ids] + p["positional_embedding"]
    causal = torch.full((length, length), float("-inf")).triu(1)
    for i in range(TEXT["layers"]):
        x = _resblock(x, p, f"transformer.resblocks.{i}.", TEXT["heads"], causal)
    x = F.layer_norm(x, (TEXT["width"],), p["ln_final.weight"], p["ln_final.bias"], 1e-5)
    pooled = x[torch.arange(len(ids)), ids.argmax(dim=-1)]
    return F.normalize(pooled @ p["text_projection"], dim=-1)


def open_clip_image(p: dict, pixels: torch.Tensor) -> torch.Tensor:
    """pixels [n, 3, S, S] in [0, 1]."""
    x = F.conv2d((pixels - MEAN) / STD, p["visual.conv1.weight"], stride=VISION["patch_size"])
    x = x.flatten(2).transpose(1, 2)
    cls = p["visual.class_embedding"].expand(len(x), 1, -1)
    x = torch.cat([cls, x], dim=1) + p["visual.positional_embedding"]
    width = VISION["width"]
    x = F.layer_norm(x, (width,), p["visual.ln_pre.weight"], p["visual.ln_pre.bias"], 1e-5)
    for i in range(VISION["layers"]):
        x = _resblock(x, p, f"visual.transformer.resblocks.{i}.", width // 64, None)
    pooled = F.layer_norm(
        x[:, 0], (width,), p["visual.ln_post.weight"], p["visual.ln_post.bias"], 1e-5
    )
    return F.normalize(pooled @ p["visual.proj"], dim=-1)


def open_clip_ids(texts: list[str]) -> torch.Tensor:
    tok = _tokenizer()
    rows = [tok(text)["input_ids"] for text in texts]
    ids = torch.zeros((len(rows), TEXT["context_length"]), dtype=torch.long)
    for i, row in enumerate(rows):
        ids[i, : len(row)] = torch.tensor(row)
    return ids


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return write_open_clip(tmp_path_factory.mktemp("openclip") / "tiny-openclip")


def test_text_features_equal_open_clips_forward(folder):
    texts = ["mug", "the mugs handle", "a", "teddy bear nose"]
    weights = open_clip_weights(len(_tokenizer()))
    expected = open_clip_text(weights, open_clip_ids(texts)).numpy()
    encoder = CLIPTextEncoder(space="someone/tiny-openclip", model_path=folder)
    assert encoder.dim == EMBED
    got = encoder.encode(texts)
    assert got.shape == (4, EMBED)
    assert abs(got - expected).max() < 1e-5
    # the texts are not alike: a wrong pooling or attention split would not pass by chance
    assert (expected @ expected.T)[~torch.eye(4, dtype=torch.bool).numpy()].max() < 0.999


def test_image_features_equal_open_clips_forward(folder):
    pixels = torch.rand((3, 3, 32, 32), generator=torch.Generator().manual_seed(1))
    weights = open_clip_weights(len(_tokenizer()))
    encoder = CLIPImageEncoder("someone/tiny-openclip", folder)
    assert (encoder.dim, encoder.image_size) == (EMBED, 32)
    got = encoder.encode(pixels)
    assert torch.allclose(got, open_clip_image(weights, pixels), atol=1e-5)


def test_read_from_the_hugging_face_cache_by_id(folder, tmp_path, monkeypatch):
    cache = tmp_path / "hub"
    repo = cache / "models--someone--tiny-openclip"
    snapshot = repo / "snapshots" / ("a" * 40)
    shutil.copytree(folder, snapshot)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("a" * 40)
    # huggingface_hub reads $HF_HUB_CACHE when imported: point its constant at this cache
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(cache))
    by_id = CLIPTextEncoder(space="someone/tiny-openclip").encode(["mug"])
    by_folder = CLIPTextEncoder(space="someone/tiny-openclip", model_path=folder).encode(["mug"])
    assert (by_id == by_folder).all()
    # the cache folder names its space, as for transformers-format models
    assert clip_space(snapshot) == "someone/tiny-openclip"


def test_a_folder_named_like_langsplats_model_is_its_space(tmp_path):
    named = write_open_clip(tmp_path / "CLIP-ViT-B-16-laion2B-s34B-b88K")
    assert clip_space(named) == LANGSPLAT_SPACE


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda w, c: c["model_cfg"]["vision_cfg"].update(ls_init_value=0.1), "ls_init_value"),
        (lambda w, c: c["model_cfg"]["text_cfg"].pop("layers"), "text_cfg.layers"),
        (lambda w, c: w.pop("visual.proj"), "has no parameter 'visual.proj'"),
        (lambda w, c: w.update({"visual.attn_pool.query": torch.zeros(2)}), "visual.attn_pool"),
        (lambda w, c: w.update({"visual.proj": torch.zeros(3, 3)}), "visual_projection.weight"),
    ],
)
def test_checkpoints_it_cannot_read_are_refused_by_name(tmp_path, change, message):
    weights = open_clip_weights(len(_tokenizer()))
    tok = len(_tokenizer())
    config = {
        "model_cfg": {
            "embed_dim": EMBED,
            "vision_cfg": dict(VISION),
            "text_cfg": dict(TEXT, vocab_size=tok),
        }
    }
    change(weights, config)
    bad = write_open_clip(tmp_path / "bad", weights=weights, config=config)
    with pytest.raises(InputError, match=message) as caught:
        CLIPImageEncoder("someone/bad", bad)
    assert str(bad) in str(caught.value)


def test_missing_weights_and_tokenizer_are_named(tmp_path):
    no_weights = write_open_clip(tmp_path / "a")
    (no_weights / "open_clip_model.safetensors").unlink()
    with pytest.raises(InputError, match="without weights"):
        CLIPImageEncoder("someone/a", no_weights)
    no_tokenizer = write_open_clip(tmp_path / "b", tokenizer=False)
    with pytest.raises(InputError, match="without tokenizer files"):
        CLIPTextEncoder(space="someone/b", model_path=no_tokenizer)
    with pytest.raises(ThgsError, match=r"no config\.json"):
        CLIPTextEncoder(space="someone/c", model_path=tmp_path)
