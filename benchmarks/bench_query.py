"""Query latency, 2D mask rendering and picking on a synthetic field.

    .venv/bin/python benchmarks/bench_query.py                          # synth-small, medium
    .venv/bin/python benchmarks/bench_query.py --presets synth-medium --seeds 0

Each (preset, seed) runs in its own process: the scene is generated, the synthetic oracle's
guidance (default severity 0.5) is made with the offline MiniLM text model, and the field is built
with the LERF preset (not timed here: see bench_build.py). Then, on that field:

- query latency for 1 and for 100 prompts, per selection mode, with the text embeddings already
  cached (the goal: ≤ 10 ms for a query over the whole field) and with text encoding included
  (new texts, so the model runs);
- opening a :class:`thgs.query.FieldQuery` (encoding the canonical phrases, grouping members);
- 2D masks per view: the selection's rendered opacity for 1 query and for 100 queries in one pass;
- picking one pixel.

Times are medians over repetitions. One JSON line per run, then a markdown table.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch
from bench_partition import oracle_views, runs_in_subprocesses

from thgs.pipeline import FieldConfig, build_field
from thgs.query import FieldQuery, QueryConfig
from thgs.synthetic import OracleConfig, generate_scene, preset
from thgs.text import MINILM_SPACE, load_text_encoder
from thgs.views import pick, selection_masks

MODES = {
    "auto": QueryConfig(),
    "paper": QueryConfig(mode="paper"),
    "level": QueryConfig(mode="level", level=2),
    "threshold": QueryConfig(mode="threshold", level=3),
}


def median_ms(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return round(1e3 * statistics.median(times), 3)


def prompts(names: list[str], count: int) -> list[str]:
    """``count`` distinct prompts: the scene's names, then templated variants of them."""
    texts = list(dict.fromkeys(names))
    templates = ("a {}", "the {}", "a photo of a {}", "part of a {}", "a small {}", "an old {}")
    for template in templates:
        texts += [template.format(name) for name in dict.fromkeys(names)]
    return texts[:count]


def run_one(name: str, seed: int) -> dict:
    encoder = load_text_encoder(MINILM_SPACE)
    scene = generate_scene(preset(name, seed=seed))
    oracle = OracleConfig(seed=seed)
    views = oracle_views(scene, encoder, oracle)
    field = build_field(scene, views, FieldConfig.lerf(), space=encoder.space)
    names = [n for level in scene.hierarchy.names.values() for n in level]
    hundred = prompts(names, 100)
    assert len(hundred) == 100

    result: dict = {
        "preset": name,
        "seed": seed,
        "gaussians": len(field),
        "region_counts": list(field.region_counts),
        "threads": torch.get_num_threads(),
        "open_ms": median_ms(lambda: FieldQuery(field, encoder), 5),
    }
    fresh = iter(range(10**6))  # a new suffix per call: new texts, so the model runs
    for mode, config in MODES.items():
        for count, texts in (("1", hundred[:1]), ("100", hundred)):

            def cached(texts=texts, config=config):
                fq = FieldQuery(field, encoder, config)
                fq.embed(texts)
                started = time.perf_counter()
                fq.select(texts)
                return time.perf_counter() - started

            result[f"{mode}_{count}_ms"] = round(
                1e3 * statistics.median(cached() for _ in range(7)), 3
            )

        def encoded(config=config):
            rep = next(fresh)
            fq = FieldQuery(field, encoder, config)
            fq.select([f"{text} #{rep}" for text in hundred])

        result[f"{mode}_100_encoded_ms"] = median_ms(encoded, 3)
    selections = FieldQuery(field, encoder).select(hundred)
    one = selections[0].gaussians
    stacked = np.stack([s.gaussians for s in selections], axis=1)
    camera = scene.cameras.select([0])
    result["mask_1_ms"] = median_ms(lambda: selection_masks(scene.gaussians, camera, one), 3)
    result["mask_100_ms"] = median_ms(lambda: selection_masks(scene.gaussians, camera, stacked), 3)
    width, height = int(camera.widths[0]), int(camera.heights[0])
    result["pick_ms"] = median_ms(
        lambda: pick(field, scene.gaussians, camera, (width // 2, height // 2)), 5
    )
    return result


def main() -> None:
    runs = runs_in_subprocesses(__doc__, __file__, run_one)
    columns = [
        ("preset", "preset"),
        ("gaussians", "N"),
        ("auto_1_ms", "auto 1 (ms)"),
        ("auto_100_ms", "auto 100"),
        ("paper_1_ms", "paper 1"),
        ("level_1_ms", "level 1"),
        ("threshold_1_ms", "thresh 1"),
        ("auto_100_encoded_ms", "auto 100 + text"),
        ("open_ms", "open"),
        ("mask_1_ms", "mask 1 (ms/view)"),
        ("mask_100_ms", "mask 100"),
        ("pick_ms", "pick"),
    ]
    print("| " + " | ".join(title for _, title in columns) + " |")
    print("|" + "---|" * len(columns))
    for run in runs:
        print(
            "| "
            + " | ".join(
                f"{run[key]:,}" if key == "gaussians" else str(run[key]) for key, _ in columns
            )
            + " |"
        )


if __name__ == "__main__":
    main()
