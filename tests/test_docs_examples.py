"""Every ```python example of the README and docs/*.md runs, on the small synthetic dataset.

Each file's examples run in order in one namespace, in a fresh folder where the paths the docs
use (``output/garden``, ``data/teatime``, ``scene.thgs``, ``lerf_ovs/label/teatime`` …) lead to the
small dataset and its field. A few examples are fragments that take a name from the text around
them (``query``, ``lifted``); :data:`GIVEN` defines those before the example, and nothing else.
A block preceded by ``<!-- signatures: MODULE -->`` lists signatures rather than code: every name
it lists must exist in MODULE. A block preceded by ``<!-- not-run: REASON -->`` is compiled only.
"""

from __future__ import annotations

import importlib
import os
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
DOCS = [
    path
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    if "```python" in path.read_text()
]
BLOCK = re.compile(r"(?:<!-- (signatures|not-run): ([^>]*?) -->\n)?```python\n(.*?)```", re.S)

GIVEN = {
    ("features.md", 0): "scene = thgs.load_scene('data/teatime')"
    "\nguidance = load_guidance('data/teatime/language_features', scene.cameras)"
    "\nlabels = load_field('scene.thgs').labels[:, 2]  # [N] the parts",
    ("field.md", 2): "query = np.array([0.0, 0.0, 1.0], np.float32)",
    ("lifting.md", 0): "scene = thgs.load_scene('scene')",
    ("partition.md", 1): "gaussians = scene.gaussians"
    "\nlifted = lift_views(scene.gaussians, scene.cameras, guidance)",
}
"""(file, block index) → what the surrounding text gives the fragment."""

GIVEN_IMPORTS = (
    "import numpy as np\nimport thgs\nfrom thgs.field import load_field\n"
    "from thgs.guidance import load_guidance\nfrom thgs.lift import lift_views\n"
)


def blocks(path: Path) -> list[tuple[str | None, str, str]]:
    """(marker, marker argument, code) of every python block of a markdown file."""
    return [(m or None, arg.strip(), code) for m, arg, code in BLOCK.findall(path.read_text())]


def workspace(folder: Path, dataset: Path, field: Path) -> None:
    """The paths the docs use, leading to the small dataset and its field."""
    for name in ("output/garden", "output/teatime", "data/teatime", "scene", "lerf_ovs/teatime"):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).symlink_to(dataset, target_is_directory=True)
    (folder / "lerf_ovs/label").mkdir(parents=True)
    (folder / "lerf_ovs/label/teatime").symlink_to(dataset / "label", target_is_directory=True)
    ply = next(dataset.glob("point_cloud/iteration_*/point_cloud.ply"))
    (folder / "point_cloud.ply").symlink_to(ply)
    garden = folder / "data/garden"
    garden.mkdir(parents=True)
    for name in ("sparse", "language_features"):
        (garden / name).symlink_to(dataset / name, target_is_directory=True)
    (garden / "images_4").mkdir()
    for image in sorted((dataset / "images").iterdir()):
        with Image.open(image) as full:
            full.resize((full.width // 4, full.height // 4)).save(garden / "images_4" / image.name)
    for name in ("scene.thgs", "teatime.thgs", "scene/field.safetensors"):
        if not (folder / name).exists():
            (folder / name).symlink_to(field)


@pytest.mark.slow
@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_examples_run(path, small_dataset, small_field, tmp_path, monkeypatch):
    found = blocks(path)
    workspace(tmp_path, small_dataset, small_field)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(GIVEN_IMPORTS, namespace)
    for index, (marker, argument, code) in enumerate(found):
        where = f"{path.name} example {index + 1}"
        if marker == "signatures":
            module = importlib.import_module(argument)
            names = re.findall(r"^([A-Za-z_]\w*)\s*(?:\(|=|#|$)", code, re.M)
            assert names, where
            assert [n for n in names if not hasattr(module, n)] == [], where
            continue
        compiled = compile(code, where, "exec")
        if marker == "not-run":
            continue
        if (path.name, index) in GIVEN:
            exec(GIVEN[(path.name, index)], namespace)
        exec(compiled, namespace)


def test_the_workspace_is_what_the_docs_say(small_dataset, small_field, tmp_path):
    workspace(tmp_path, small_dataset, small_field)
    assert (tmp_path / "scene.thgs").resolve() == small_field.resolve()
    images = sorted((tmp_path / "data/garden/images_4").iterdir())
    with (
        Image.open(images[0]) as image,
        Image.open(small_dataset / "images" / images[0].name) as full,
    ):
        assert image.size == (full.width // 4, full.height // 4)
    assert os.path.samefile(tmp_path / "output/teatime", small_dataset)
    assert np.all([p.exists() for p in (tmp_path / "lerf_ovs/label/teatime").iterdir()])
