"""``lerf-opengaussian``: LERF-OVS under OpenGaussian's rule: silhouettes > 0.7 and, for its
four scenes, only its fixed prompt lists (:func:`thgs.eval.evaluate_lerf_opengaussian`). Which
list applies follows from the scene's name alone (the dataset folder's, e.g. ``teatime``); the
result's note says which list applied and why, and reports print it under the table."""

from __future__ import annotations

from thgs.eval.evaluate import evaluate_lerf_opengaussian
from thgs.eval.protocols import Protocol, register_protocol
from thgs.eval.protocols.lerf import frames

__all__: list[str] = []

register_protocol(
    Protocol(
        name="lerf-opengaussian",
        summary="silhouette > 0.7",
        source="lerf",
        needs_cameras=True,
        headline=(("lerf-opengaussian", "miou"),),
        evaluate=lambda c: [
            evaluate_lerf_opengaussian(
                c.engine,
                c.gaussians,
                c.cameras,
                frames(c),
                scene_name=c.scene_name,
                raster=c.raster,
                progress=c.progress,
                rescale_labels=c.options.get("rescale_labels", False),
            )
        ],
    )
)
