"""How large a scene ``thgs view`` keeps interactive: the server's time and bytes per action.

    .venv/bin/python benchmarks/bench_viewer.py                          # 50k, 200k, 1M, 2M
    .venv/bin/python benchmarks/bench_viewer.py --copies 1 4 --repeat 5

The demo's synth-small field (50,000 Gaussians, built once and cached like ``thgs demo``) is
tiled side by side ``copies`` times into one larger scene and field (every region copied, ids
offset, so the hierarchy and the features are the demo's), shown by a real viser server with
the default 65,536-Gaussian chunks, and each action is timed as the viewer runs it: the state
change plus re-sending the colours (packing and queuing the chunks that changed). What a browser
then does with the bytes (its GPU upload and sort) is not measured: it depends on the browser's
GPU, and this machine has none.

Actions, medians over ``--repeat``:

- ``open``: the splats: covariances, hierarchy order, packing, queuing every chunk (once);
- ``query``: a text query whose highlight differs from the last (embedding cached);
- ``index``: building the scene's pick index (once, when the viewer opens the field);
- ``pick``: a click through ``ViewerState.pick`` (one pixel at the viewport's 1200×800, only
  the Gaussians near the clicked ray rasterized) on another object; ``candidates``: how many
  Gaussians that rasterized, median over the clicks;
- ``level``: the level selector moving the picked region up one level;
- ``clear``: back to the scene's colours;
- ``mask``: the 2D mask of the current view at 480 px tall.

Bytes are the splat buffers queued for the browser by that action (32 per Gaussian of each
chunk re-sent).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from thgs.demo import run_demo
from thgs.field import SemanticField, scene_fingerprint
from thgs.field_scene import open_field_scene
from thgs.pick_index import PickIndex
from thgs.query import FieldQuery
from thgs.scene import Gaussians
from thgs.text import load_text_encoder
from thgs.viewer.splats import SplatChunks, hierarchy_order, splat_covariances
from thgs.viewer.state import ViewerConfig, ViewerState


def tiled(field: SemanticField, gaussians: Gaussians, copies: int):
    """``copies`` side-by-side copies of a scene and its field (x offset by 1.2 × its width)."""
    means = gaussians.means
    width = float(means[:, 0].max() - means[:, 0].min()) * 1.2
    offsets = torch.zeros(copies, 1, 3, dtype=means.dtype)
    offsets[:, 0, 0] = width * torch.arange(copies, dtype=means.dtype)
    big = Gaussians(
        means=(means[None] + offsets).reshape(-1, 3),
        quats=gaussians.quats.repeat(copies, 1),
        scales=gaussians.scales.repeat(copies, 1),
        opacities=gaussians.opacities.repeat(copies),
        sh=gaussians.sh.repeat(copies, 1, 1),
    )
    counts = np.array(field.region_counts)
    labels = np.concatenate([field.labels + c * counts for c in range(copies)])
    parents = tuple(
        np.concatenate([p + c * counts[k + 1] for c in range(copies)]).astype(np.int32)
        for k, p in enumerate(field.parents)
    )
    big_field = replace(
        field,
        labels=labels.astype(np.int32),
        parents=parents,
        features=tuple(np.tile(f, (copies, 1)) for f in field.features),
        seen=tuple(np.tile(s, copies) for s in field.seen),
        fingerprint=scene_fingerprint(big),
    ).check()
    return big_field, big


def _median_ms(run, repeat: int) -> float:
    times = []
    for i in range(repeat):
        start = time.perf_counter()
        run(i)
        times.append(time.perf_counter() - start)
    return 1000.0 * statistics.median(times)


def bench(field: SemanticField, gaussians: Gaussians, cameras, encoder, repeat: int) -> dict:
    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        state = ViewerState(field, gaussians, FieldQuery(field, encoder), ViewerConfig())
        result = {"gaussians": len(gaussians), "regions": list(field.region_counts[1:])}
        splats: list[SplatChunks] = []

        def open_splats(i: int) -> None:
            if splats:
                splats.pop().remove()
            rgb, opacity = state.colors()
            splats.append(
                SplatChunks(
                    server.scene,
                    "/scene",
                    gaussians.means.numpy(),
                    splat_covariances(gaussians),
                    rgb,
                    opacity,
                    order=hierarchy_order(field.labels),
                )
            )

        result["open_ms"] = _median_ms(open_splats, max(1, repeat // 2))
        chunks = splats[0]
        result["chunks"] = chunks.chunk_count

        def timed(action) -> tuple[float, float]:
            def run(i: int) -> None:
                action(i)
                chunks.update(*state.colors())

            sent = chunks.bytes_sent
            ms = _median_ms(run, repeat)
            return ms, (chunks.bytes_sent - sent) / repeat / 2**20

        texts = ["teddy bear", "mug", "chair", "table"]
        state.query.embed(texts)
        result["query_ms"], result["query_MiB"] = timed(lambda i: state.ask(texts[i % 4]))
        camera = cameras.select([0]).resized([1200], [800])
        pixels = [(600, 400), (400, 500), (800, 300)]
        result["index_ms"] = _median_ms(lambda i: PickIndex.build(gaussians), max(1, repeat // 2))
        counts = [len(state.pick_index.candidates(gaussians, camera, p)) for p in pixels]
        result["candidates"] = int(statistics.median(counts))
        state.set_level(3)
        result["pick_ms"], result["pick_MiB"] = timed(
            lambda i: state.pick(camera, pixels[i % len(pixels)])
        )
        state.set_level(1)
        result["level_ms"], result["level_MiB"] = timed(lambda i: state.set_level(1 + i % 3))
        result["clear_ms"], result["clear_MiB"] = timed(
            lambda i: state.ask(texts[0]) if i % 2 else state.clear()
        )
        state.ask(texts[0])
        mask_camera = cameras.select([0]).resized([720], [480])
        result["mask_ms"] = _median_ms(lambda i: state.view_mask(mask_camera), max(1, repeat // 2))
        return result
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, nargs="+", default=[1, 4, 20, 40])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out:
        run_demo(out)
        base_field, scene = open_field_scene(Path(out) / "field.thgs")
    encoder = load_text_encoder(base_field.space)
    rows = []
    for copies in args.copies:
        field, gaussians = tiled(base_field, scene.gaussians, copies)
        row = bench(field, gaussians, scene.cameras, encoder, args.repeat)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print()
    print(
        "| Gaussians | chunks | open ms | query ms, MiB | pick index | pick (candidates) | level "
        "| clear | mask 720×480 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['gaussians']:,} | {r['chunks']} | {r['open_ms']:.0f} "
            f"| {r['query_ms']:.0f}, {r['query_MiB']:.1f} | {r['index_ms']:.0f} "
            f"| {r['pick_ms']:.0f}, {r['pick_MiB']:.1f} ({r['candidates']:,}) "
            f"| {r['level_ms']:.0f}, {r['level_MiB']:.1f} | {r['clear_ms']:.0f}, "
            f"{r['clear_MiB']:.1f} | {r['mask_ms']:.0f} |"
        )


if __name__ == "__main__":
    main()
