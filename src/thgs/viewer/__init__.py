"""The browser viewer (``thgs view``): a viser app over the public query, pick and export API.

- :mod:`thgs.viewer.state` — what the viewer shows and does, without a browser: the selection
  (a text query or a picked region), climbing the hierarchy, display colours, the 2D mask of a
  view and exports. Unit-tested on its own.
- :mod:`thgs.viewer.camera` — the browser's viewport camera as a :class:`thgs.scene.Cameras`.
- :mod:`thgs.viewer.splats` — the scene's Gaussians as viser splat nodes, sent once; colour
  changes re-send only the chunks whose colours changed.
- :mod:`thgs.viewer.app` — the viser GUI wiring, and :func:`~thgs.viewer.app.start_viewer`.

See docs/viewer.md.
"""

__all__: list[str] = []
