"""Text encoders: CLIP through transformers with a randomly initialised small model and a tiny
tokenizer built here, the offline MiniLM model, and the space checks."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

from thgs.errors import InputError, ThgsError
from thgs.text import (
    LANGSPLAT_SPACE,
    MINILM_SPACE,
    CLIPTextEncoder,
    MiniLMEncoder,
    SpaceMismatchError,
    check_space,
    clip_space,
    known_dim,
    load_text_encoder,
)

transformers = pytest.importorskip("transformers")

import tiny_models  # noqa: E402  (needs transformers)

SPACE = "test/tiny-clip"


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    return tiny_models.tiny_clip(tmp_path_factory.mktemp("tiny-clip"))


def test_clip_encoder_gives_the_models_normalized_text_features(tiny_clip):
    encoder = load_text_encoder(SPACE, model_path=tiny_clip)
    assert isinstance(encoder, CLIPTextEncoder)
    assert (encoder.space, encoder.dim) == (SPACE, 16)
    texts = ["a mug", "teddy bear", "the mugs handle"]
    embeddings = encoder.encode(texts)
    assert embeddings.shape == (3, 16) and embeddings.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(embeddings, axis=1), 1.0, rtol=1e-6)

    # by hand: tokenize one phrase, run the text tower and the projection, normalize
    model = transformers.CLIPModel.from_pretrained(tiny_clip).eval()
    tokenizer = transformers.AutoTokenizer.from_pretrained(tiny_clip)
    tokens = tokenizer(["teddy bear"], return_tensors="pt")
    ids = tokens["input_ids"][0]
    assert ids[0] == tokenizer.bos_token_id and ids[-1] == tokenizer.eos_token_id
    assert len(ids) == len("teddybear") + 2  # one token per letter, start and end
    with torch.no_grad():
        # CLIP's text feature: the final (layer-normed) state of the end token, projected
        hidden = model.text_model(**tokens).last_hidden_state[0, -1]
        reference = model.text_projection(hidden).numpy()
    np.testing.assert_allclose(
        embeddings[1], reference / np.linalg.norm(reference), rtol=1e-5, atol=1e-6
    )


def test_clip_embeddings_do_not_depend_on_the_batch(tiny_clip):
    together = CLIPTextEncoder(SPACE, tiny_clip).encode(["a mug", "a much longer phrase here"])
    alone = CLIPTextEncoder(SPACE, tiny_clip).encode(["a mug"])
    np.testing.assert_allclose(together[0], alone[0], rtol=1e-5, atol=1e-6)
    encoder = CLIPTextEncoder(SPACE, tiny_clip)
    first = encoder.encode(["a mug", "a mug"])
    np.testing.assert_array_equal(first[0], first[1])
    assert encoder.encode([]).shape == (0, 16)


def test_missing_clip_weights_say_what_to_download(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ThgsError, match="hf download laion/CLIP-ViT-B-16-laion2B-s34B-b88K"):
        load_text_encoder("laion/CLIP-ViT-B-16-laion2B-s34B-b88K")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ThgsError, match=r"no config\.json"):
        CLIPTextEncoder(SPACE, empty)
    (empty / "config.json").write_text(json.dumps({"model_type": "clip"}))
    with pytest.raises(ThgsError, match=f"CLIP weights for '{SPACE}' not found in {empty}"):
        CLIPTextEncoder(SPACE, empty)


def test_minilm_encoder_is_offline_and_unit_length():
    pytest.importorskip("sentence_transformers")
    encoder = load_text_encoder(MINILM_SPACE)
    assert isinstance(encoder, MiniLMEncoder) and encoder.dim == 384
    rows = encoder.encode(["mug", "teddy bear", "mug"])
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(rows[0], rows[2])
    # related words are closer than unrelated ones
    cup, giraffe = encoder.encode(["cup", "giraffe"])
    assert rows[0] @ cup > rows[0] @ giraffe


def test_minilm_encoders_share_one_loaded_model(monkeypatch):
    sentence_transformers = pytest.importorskip("sentence_transformers")
    loads = []
    real = sentence_transformers.SentenceTransformer

    def counted(*args, **kwargs):
        loads.append(kwargs["device"])
        return real(*args, **kwargs)

    monkeypatch.setattr(sentence_transformers, "SentenceTransformer", counted)
    # a device string no other test uses: its model is not loaded yet in this process
    encoders = [MiniLMEncoder(device="cpu:0") for _ in range(4)]
    assert loads == ["cpu:0"]
    # the encoders take turns on the shared model: the same phrases from four threads at once
    phrases = [f"a thing numbered {i}" for i in range(12)]
    with ThreadPoolExecutor(4) as pool:
        rows = list(pool.map(lambda encoder: encoder.encode(phrases), encoders))
    for other in rows[1:]:
        np.testing.assert_array_equal(rows[0], other)
    np.testing.assert_array_equal(rows[0], MiniLMEncoder().encode(phrases))


def test_space_check_names_both_spaces(tiny_clip):
    encoder = CLIPTextEncoder(SPACE, tiny_clip)
    check_space(SPACE, encoder, "scene.thgs")
    with pytest.raises(SpaceMismatchError, match=r"scene.thgs: .*'other/space'.*'test/tiny-clip'"):
        check_space("other/space", encoder, "scene.thgs")


def test_a_local_folder_that_is_no_hub_id_gets_no_download_hint(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    gone = str(tmp_path / "gone-clip")
    with pytest.raises(ThgsError) as caught:
        load_text_encoder(gone)
    message = str(caught.value)
    assert "not a Hugging Face model id" in message and "--text-model DIR" in message
    assert "hf download" not in message


def test_a_folder_of_another_dimension_is_not_a_known_space(tiny_clip):
    with pytest.raises(
        InputError, match=rf"gives 16-D text embeddings but {LANGSPLAT_SPACE} is 512"
    ):
        CLIPTextEncoder(LANGSPLAT_SPACE, tiny_clip)
    assert (known_dim(LANGSPLAT_SPACE), known_dim(MINILM_SPACE), known_dim(SPACE)) == (
        512,
        384,
        None,
    )


def test_space_check_compares_dimensions(tiny_clip):
    encoder = CLIPTextEncoder(SPACE, tiny_clip)
    check_space(SPACE, encoder, "scene.thgs", dim=16)
    with pytest.raises(
        SpaceMismatchError, match=r"scene.thgs: features are 512-D but the text model"
    ):
        check_space(SPACE, encoder, "scene.thgs", dim=512)


def _clip_folder(folder: Path, config: dict) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"model_type": "clip", **config}))
    return folder


def test_clip_space_reads_the_folders_hugging_face_id(tmp_path):
    snapshot = tmp_path / "hub" / "models--openai--clip-vit-base-patch16" / "snapshots" / "abc123"
    assert clip_space(_clip_folder(snapshot, {})) == "openai/clip-vit-base-patch16"
    saved = _clip_folder(tmp_path / "saved", {"_name_or_path": "openai/clip-vit-large-patch14"})
    assert clip_space(saved) == "openai/clip-vit-large-patch14"
    # hf download laion/CLIP-ViT-B-16-laion2B-s34B-b88K --local-dir CLIP-ViT-B-16-laion2B-s34B-b88K
    local = _clip_folder(tmp_path / "models" / "CLIP-ViT-B-16-laion2B-s34B-b88K", {})
    assert clip_space(local) == LANGSPLAT_SPACE
    # a path in _name_or_path (a model saved from a folder) or none at all: the folder itself
    own = _clip_folder(tmp_path / "finetuned", {"_name_or_path": "/data/runs/clip"})
    assert clip_space(own) == str(own.resolve())
    with pytest.raises(InputError, match=r"no config\.json"):
        clip_space(tmp_path)
