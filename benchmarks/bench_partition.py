"""Time and peak memory of the level-0 partition stages on the synthetic presets, with purity.

    .venv/bin/python benchmarks/bench_partition.py                         # synth-small, medium
    .venv/bin/python benchmarks/bench_partition.py --presets synth-small --seeds 0 1 2

Each (preset, seed) runs in its own process. The guidance is the synthetic oracle's at its default
fault severity (0.5), with hash features instead of MiniLM ones (the partition never reads the
features). Stages run one by one as in :func:`thgs.pipeline.partition_scene`: lift (latent,
CPU rasterizer), KNN graph, edge votes, reweighting, cut pursuit. The peak resident memory of a
stage is sampled every 5 ms by a thread reading /proc/self/statm (Linux), so it counts what the
process already held. Then the graph stages are rerun without reweighting and with the
reference's behaviour (:meth:`SuperpointConfig.as_reference`) on the same lift, and the sub-part,
part and object purity of each partition is reported with its superpoint count.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import zlib
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from thgs.bench import measured as measure
from thgs.eval import purity
from thgs.graph import ReweightConfig, edge_counts, knn_graph, partition, reweight
from thgs.lift import lift_views
from thgs.pipeline import SuperpointConfig
from thgs.synthetic import OracleConfig, generate_scene, oracle_guidance, preset, render_view


class HashEncoder:
    """Unit vectors seeded by the phrase: stand-ins for text features the partition ignores."""

    space = "bench/hash"
    dim = 16

    def encode(self, texts):
        rows = [np.random.default_rng(zlib.crc32(t.encode())).normal(size=16) for t in texts]
        rows = np.array(rows, dtype=np.float64).reshape(-1, 16)
        return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def measured(function: Callable, *args):
    """``(result, seconds, peak RSS GiB while it ran)``, rounded: :func:`thgs.bench.measured`."""
    result, seconds, peak_gib, _ = measure(lambda: function(*args))
    return result, round(seconds, 2), round(peak_gib, 2)


def oracle_views(scene, encoder, oracle: OracleConfig) -> list:
    """The oracle's guidance for every camera of a synthetic scene, rendered on white."""
    views = []
    for i, stem in enumerate(scene.cameras.stems):
        _, max_id = render_view(scene, i, (1.0, 1.0, 1.0))
        views.append(oracle_guidance(stem, max_id, scene.hierarchy, encoder, oracle, i))
    return views


def graph_stages(gaussians, lifted, config: SuperpointConfig) -> tuple[np.ndarray, dict]:
    graph, knn_s, knn_gib = measured(knn_graph, gaussians, config.graph)
    (pos, neg), votes_s, votes_gib = measured(edge_counts, graph, lifted, config.reweight)
    distances, reweight_s, reweight_gib = measured(reweight, graph, pos, neg, config.reweight)
    labels, partition_s, partition_gib = measured(
        partition, gaussians, graph, distances, config.partition
    )
    return labels, {
        "knn": (knn_s, knn_gib),
        "votes": (votes_s, votes_gib),
        "reweight": (reweight_s, reweight_gib),
        "partition": (partition_s, partition_gib),
    }


def run_one(name: str, seed: int) -> dict:
    scene, generate_s, _ = measured(generate_scene, preset(name, seed=seed))
    encoder, oracle = HashEncoder(), OracleConfig(seed=seed)

    views, guidance_s, _ = measured(oracle_views, scene, encoder, oracle)
    config = SuperpointConfig()
    lifted, lift_s, lift_gib = measured(
        lift_views, scene.gaussians, scene.cameras, views, config.lift
    )
    truth = scene.hierarchy.labels
    variants = {
        "ours": config,
        "none": replace(config, reweight=ReweightConfig(mode="none")),
        "reference": config.as_reference(),
    }
    results = {}
    for variant, variant_config in variants.items():
        labels, stages = graph_stages(scene.gaussians, lifted, variant_config)
        results[variant] = {
            "superpoints": int(labels.max()) + 1,
            "purity": [round(purity(labels, truth[:, level]), 4) for level in (1, 2, 3)],
            "stages": stages,
        }
    return {
        "preset": name,
        "seed": seed,
        "gaussians": len(scene.gaussians),
        "views": len(scene.cameras),
        "threads": torch.get_num_threads(),
        "setup_s": {"generate": generate_s, "oracle_guidance": guidance_s},
        "lift": (lift_s, lift_gib),
        "labelled_share": round(
            sum(int((v.labels[:, 1] >= 0).sum()) for v in lifted) / sum(len(v) for v in lifted), 3
        ),
        "variants": results,
    }


def runs_in_subprocesses(
    doc: str,
    script: str,
    run_one: Callable[..., dict],
    options: Callable[[argparse.ArgumentParser], None] | None = None,
) -> list[dict]:
    """Parse ``--presets`` and ``--seeds`` (and what ``options`` adds), run every (preset, seed)
    in its own process and return the runs, printing each as a JSON line. The child process
    (``script`` with the same arguments and ``--one``) prints ``run_one(preset, seed)`` (with the
    parsed arguments as a third argument when ``options`` is given) as JSON and exits."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--presets", nargs="*", default=["synth-small", "synth-medium"])
    parser.add_argument("--seeds", type=int, nargs="*", default=[0])
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    if options is not None:
        options(parser)
    args = parser.parse_args()
    if args.one:
        extra = (args,) if options is not None else ()
        print(json.dumps(run_one(args.presets[0], args.seeds[0], *extra)))
        raise SystemExit(0)
    runs = []
    for name in args.presets:
        for seed in args.seeds:
            command = [
                sys.executable, script, *sys.argv[1:], "--one", "--presets", name,
                "--seeds", str(seed),
            ]  # fmt: skip
            result = subprocess.run(command, capture_output=True, text=True, check=True)
            print(result.stdout.strip(), flush=True)
            runs.append(json.loads(result.stdout))
    return runs


def main() -> None:
    runs_in_subprocesses(__doc__, __file__, run_one)


if __name__ == "__main__":
    main()
