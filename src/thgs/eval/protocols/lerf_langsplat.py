"""``lerf-langsplat``: LERF-OVS under LangSplat's 2D rule: per-level relevancy maps, the level
with the highest smoothed peak, mask IoU and box localization
(:func:`thgs.eval.evaluate_lerf_langsplat`)."""

from __future__ import annotations

from thgs.eval.evaluate import evaluate_lerf_langsplat
from thgs.eval.protocols import Protocol, register_protocol
from thgs.eval.protocols.lerf import frames

__all__: list[str] = []

register_protocol(
    Protocol(
        name="lerf-langsplat",
        summary="2D relevancy maps",
        source="lerf",
        needs_cameras=True,
        headline=(("lerf-langsplat", "miou"), ("lerf-langsplat", "localization")),
        evaluate=lambda c: [
            evaluate_lerf_langsplat(
                c.engine,
                c.gaussians,
                c.cameras,
                frames(c),
                raster=c.raster,
                progress=c.progress,
                rescale_labels=c.options.get("rescale_labels", False),
            )
        ],
    )
)
