"""A vocabulary answered in one pass (``thgs catalog``) on a built field, phase by phase.

    .venv/bin/python benchmarks/bench_catalog.py FIELD [--phrases 50] [--repeats 3]

FIELD is a field built on a synthetic dataset (``thgs synth`` + ``thgs build``): the vocabulary
is the dataset's ground-truth names (objects, parts, sub-parts), then templated variants of them
("a mug", "the mug" …) up to ``--phrases``. Timed: opening the field and its scene, the query
engine (the text model loaded, the canonical and null phrases encoded), the catalog (every phrase
selected and the overlaps resolved; new text each repeat, so the model encodes every phrase),
writing its files without pictures, and writing them with a picture per phrase found (its best
view found among the scene's cameras, rendered and tinted). Medians over ``--repeats``; one JSON
line, then a markdown table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from thgs.catalog import catalog_field, write_catalog
from thgs.eval.ground_truth import read_hierarchy
from thgs.field_scene import field_text_encoder, open_field_scene
from thgs.query import FieldQuery

TEMPLATES = ("{}", "a {}", "the {}", "a photo of a {}", "part of a {}", "a small {}")


def vocabulary(names: list[str], count: int, repeat: int) -> list[str]:
    """``count`` distinct phrases from the scene's names; ``repeat`` > 0 adds a suffix so that
    the text model encodes every phrase again."""
    phrases = [template.format(name) for template in TEMPLATES for name in dict.fromkeys(names)]
    if len(phrases) < count:
        raise SystemExit(f"the scene's names give {len(phrases)} phrases, fewer than {count}")
    return [phrase + (f" #{repeat}" if repeat else "") for phrase in phrases[:count]]


def seconds(function):
    started = time.perf_counter()
    value = function()
    return value, time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("field", type=Path)
    parser.add_argument("--phrases", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    (field, scene), open_s = seconds(lambda: open_field_scene(args.field))
    engine, engine_s = seconds(lambda: FieldQuery(field, field_text_encoder(field, args.field)))
    hierarchy = read_hierarchy(Path(scene.ply_path).parents[2] / "ground_truth.safetensors")
    names = [name for k in (3, 2, 1) for name in hierarchy.names[k] if name != "floor"]
    catalog_s, write_s, pictures_s = [], [], []
    with tempfile.TemporaryDirectory() as out:
        for repeat in range(args.repeats):
            phrases = vocabulary(names, args.phrases, repeat)
            catalog, took = seconds(lambda phrases=phrases: catalog_field(engine, phrases))
            catalog_s.append(took)
            _, took = seconds(
                lambda catalog=catalog, folder=Path(out) / str(repeat): write_catalog(
                    folder, catalog, scene.gaussians, engine, field_name="f"
                )
            )
            write_s.append(took)
            _, took = seconds(
                lambda catalog=catalog, folder=Path(out) / f"{repeat}-pictures": write_catalog(
                    folder,
                    catalog,
                    scene.gaussians,
                    engine,
                    field_name="f",
                    cameras=scene.cameras,
                )
            )
            pictures_s.append(took)
    result = {
        "field": str(args.field),
        "gaussians": len(field),
        "phrases": args.phrases,
        "found": sum(entry.found for entry in catalog.entries),
        "open_s": round(open_s, 3),
        "engine_s": round(engine_s, 3),
        "catalog_s": round(statistics.median(catalog_s), 3),
        "write_s": round(statistics.median(write_s), 3),
        "write_with_pictures_s": round(statistics.median(pictures_s), 3),
    }
    result["total_s"] = round(
        sum(result[key] for key in ("open_s", "engine_s", "catalog_s", "write_s")), 3
    )
    print(json.dumps(result))
    keys = (
        "gaussians",
        "phrases",
        "found",
        "open_s",
        "engine_s",
        "catalog_s",
        "write_s",
        "total_s",
        "write_with_pictures_s",
    )
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    print("| " + " | ".join(str(result[key]) for key in keys) + " |")


if __name__ == "__main__":
    main()
