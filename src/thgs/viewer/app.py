"""The viser app behind ``thgs view``: panels wired to :class:`~thgs.viewer.state.ViewerState`.

The GUI is shared by every browser connected to the server. Each control calls one method of the
state and then :meth:`ViewerApp.refresh`, which re-sends the colours (only the splat chunks whose
colours changed) and rewrites the panels. Errors never stop the server: they are logged, shown at
the top of the panel and, to the browser that caused them, as a notification.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from thgs.device import resolve_device
from thgs.errors import InputError, ThgsError
from thgs.field import load_field
from thgs.field_scene import field_text_encoder, open_field_scene
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.query import FieldQuery, default_threshold
from thgs.scene import Scene
from thgs.viewer.camera import camera_pose, click_pixel, viewport_camera, viewport_size
from thgs.viewer.guard import AccessGuard, guarded_websockets, new_token
from thgs.viewer.splats import SplatChunks, hierarchy_order, splat_covariances
from thgs.viewer.state import COLOR_MODES, QUERY_MODES, Highlight, ViewerConfig, ViewerState

__all__ = ["ViewerApp", "start_viewer"]

logger = logging.getLogger(__name__)

LEVEL_OPTIONS = ("1 sub-part", "2 part", "3 object")


def _level_option(level: int) -> str:
    return LEVEL_OPTIONS[level - 1]


class ViewerApp:
    """The viewer's GUI on one viser server.

    Args:
        server: a started ``viser.ViserServer``.
        config: the viewer's settings.
        scene: the scene to use instead of the one each field records.
        text_model: the text model's local folder, instead of the one each field records
            (:func:`thgs.field_scene.field_text_encoder`).
        device: where the scene's Gaussians are rendered (:func:`thgs.device.resolve_device`).
        export_root: the folder exports are confined to (default ``./thgs-export``): the
            "Folder" control names a folder inside it, and anything resolving outside is refused.
    """

    def __init__(
        self,
        server,
        config: ViewerConfig = ViewerConfig(),
        *,
        scene: str | os.PathLike[str] | None = None,
        text_model: str | os.PathLike[str] | None = None,
        device: str = "auto",
        export_root: str | os.PathLike[str] | None = None,
    ):
        self.server = server
        self.export_root = Path(export_root or Path.cwd() / "thgs-export").resolve()
        self.config = config.check()
        self.scene_path = scene
        self.text_model = text_model
        self.device = resolve_device(device)
        self.state: ViewerState | None = None
        self.scene: Scene | None = None
        self.splats: SplatChunks | None = None
        self.problem: str | None = None
        self.notes: list[str] = []
        self.text_off: str | None = None
        self.token: str | None = None
        self._lock = threading.RLock()
        self._field_path: Path | None = None
        self._syncing = False
        self._build_gui()
        server.scene.on_click()(self._on_scene_click)
        server.on_client_connect(self._on_connect)

    # Layout -------------------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop the server (quietly: viser prints when it stops)."""
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        self.status = gui.add_markdown("Starting…")
        with gui.add_folder("Query"):
            self.query_text = gui.add_text("Query", "", hint="what to look for, e.g. the mug")
            self.search = gui.add_button("Search", icon="search")
            self.mode = gui.add_dropdown(
                "Mode",
                tuple(QUERY_MODES),
                initial_value=self.config.mode,
                hint="; ".join(f"{k}: {v}" for k, v in QUERY_MODES.items()),
            )
            self.threshold = gui.add_slider(
                "Threshold",
                min=0.0,
                max=1.0,
                step=0.01,
                initial_value=0.5 if self.config.threshold is None else self.config.threshold,
                hint="the relevancy the threshold mode needs",
            )
            self.results = gui.add_markdown("")
        with gui.add_folder("Display"):
            self.level = gui.add_dropdown(
                "Level", LEVEL_OPTIONS, initial_value=_level_option(self.config.level)
            )
            self.colors = gui.add_dropdown(
                "Colours",
                tuple(COLOR_MODES),
                initial_value=self.config.color,
                hint="; ".join(f"{k}: {v}" for k, v in COLOR_MODES.items()),
            )
            self.clear = gui.add_button("Clear selection", icon="x")
        with gui.add_folder("Hierarchy"):
            self.picking = gui.add_checkbox(
                "Pick on click", True, hint="click a point: its region at the level shown"
            )
            self.parent = gui.add_button("Parent", icon="arrow-up", hint="one level up")
            self.child = gui.add_button(
                "Child", icon="arrow-down", hint="one level down, through the clicked point"
            )
            self.sibling = gui.add_button(
                "Next sibling", icon="arrow-right", hint="the next region with the same parent"
            )
            self.hierarchy = gui.add_markdown("")
        with gui.add_folder("2D mask", expand_by_default=False):
            self.mask_button = gui.add_button("Mask of this view", icon="photo")
            self.views = gui.add_dropdown("Go to view", ("—",), initial_value="—")
            self.mask_image = gui.add_image(np.ones((2, 2, 3)), label="mask", visible=False)
        with gui.add_folder("Export"):
            self.export_folder = gui.add_text(
                "Folder", ".", hint=f"a folder inside {self.export_root}"
            )
            self.export_button = gui.add_button("Export selection", icon="download")
            self.export_result = gui.add_markdown("")
        with gui.add_folder("Field", expand_by_default=False):
            self.field_path = gui.add_text("Field file", "")
            self.open_button = gui.add_button("Open field", icon="folder-open")

        self.search.on_click(self._handler(self._on_search))
        self.mode.on_update(self._handler(self._on_mode))
        self.threshold.on_update(self._handler(self._on_mode))
        self.level.on_update(self._handler(self._on_level))
        self.colors.on_update(self._handler(self._on_colors))
        self.clear.on_click(self._handler(lambda state, event: state.clear()))
        self.parent.on_click(self._handler(lambda state, event: state.parent()))
        self.child.on_click(self._handler(lambda state, event: state.child()))
        self.sibling.on_click(self._handler(lambda state, event: state.sibling()))
        self.mask_button.on_click(self._handler(self._on_mask))
        self.views.on_update(self._handler(self._on_view))
        self.export_button.on_click(self._handler(self._on_export))
        self.open_button.on_click(self._on_open)

    # Opening a field ----------------------------------------------------------------------------

    def open(self, field_path: str | os.PathLike[str]) -> None:
        """Show ``field_path`` on its scene (or the app's ``scene``).

        Raises:
            ThgsError: the field cannot be read or does not match the scene. The app is left as
                it was.
        """
        with self._lock:
            field, scene = open_field_scene(field_path, self.scene_path, device=self.device)
            query, self.text_off = None, None
            try:
                encoder = field_text_encoder(field, field_path, self.text_model)
                query = FieldQuery(field, encoder, source=str(field_path))
            except ThgsError as error:
                self.text_off = f"text queries are off: {error}"
                logger.warning("%s", self.text_off)
            if self.config.threshold is None:
                with self._synced():
                    self.threshold.value = default_threshold(field.space)
            level = LEVEL_OPTIONS.index(self.level.value) + 1
            settings = replace(
                self.config,
                level=level,
                mode=self.mode.value,
                threshold=float(self.threshold.value),
                color=self.colors.value,
            )
            state = ViewerState(field, scene.gaussians, query, settings)
            same_scene = (
                self.state is not None and self.state.field.fingerprint == field.fingerprint
            )
            self.state, self.scene, self._field_path = state, scene, Path(field_path)
            if not same_scene:
                self._show_scene(scene, state)
            with self._synced():
                self.field_path.value = str(field_path)
            self.query_text.disabled = self.search.disabled = query is None
            self.problem = None
            logger.info("viewer shows %s (%d Gaussians)", field_path, len(field))
            self.refresh()

    def _show_scene(self, scene: Scene, state: ViewerState) -> None:
        if self.splats is not None:
            self.splats.remove()
        rgb, opacity = state.colors()
        self.splats = SplatChunks(
            self.server.scene,
            "/scene",
            scene.gaussians.means.detach().cpu().numpy(),
            splat_covariances(scene.gaussians),
            rgb,
            opacity,
            order=hierarchy_order(state.field.labels),
            chunk_size=self.config.chunk_size,
        )
        cameras = scene.cameras
        names = cameras.stems if cameras is not None and len(cameras) else ()
        self.views.options = ("—", *names)
        self.views.value = "—"
        if names:
            centre = scene.gaussians.means.detach().cpu().numpy().mean(axis=0)
            distance = float(np.linalg.norm(cameras.centers()[0].numpy() - centre))
            pose = camera_pose(cameras, 0, max(distance, 1e-3))
            self.server.scene.set_up_direction(tuple(pose.up))
            initial = self.server.initial_camera
            initial.position, initial.look_at = tuple(pose.position), tuple(pose.look_at)
            initial.fov = pose.fov

    # Events -------------------------------------------------------------------------------------

    def _handler(self, action: Callable) -> Callable:
        """Wrap a GUI callback: run ``action(state, event)`` under the lock, then refresh;
        report errors instead of raising."""

        def run(event) -> None:
            if self._syncing:
                return
            with self._reporting(getattr(event, "client", None)):
                if self.state is None:
                    raise ThgsError("no field is open: give a field file under Field")
                action(self.state, event)
                self.problem = None  # the action went through: an earlier problem is over
                self.refresh()

        return run

    @contextlib.contextmanager
    def _synced(self) -> Iterator[None]:
        """Set GUI values from the state without their callbacks acting on it."""
        self._syncing = True
        try:
            yield
        finally:
            self._syncing = False

    @contextlib.contextmanager
    def _reporting(self, client) -> Iterator[None]:
        with self._lock:
            try:
                yield
            except ThgsError as error:
                self.report(str(error), client)
            except Exception as error:  # a bug must not stop the server
                logger.exception("viewer callback failed")
                self.report(f"internal error: {error!r}", client)

    def report(self, message: str, client=None) -> None:
        """Show ``message`` as the current problem: in the log, at the top of the panel and as a
        notification to ``client`` (the browser that caused it) if given."""
        logger.error("%s", message)
        self.problem = message
        self._update_status()
        if client is not None:
            client.add_notification("thgs", message, color="red", auto_close_seconds=10.0)

    def _on_connect(self, client) -> None:
        if self.problem is not None:
            client.add_notification("thgs", self.problem, color="red", auto_close_seconds=10.0)

    def _on_search(self, state: ViewerState, event) -> None:
        state.ask(self.query_text.value)

    def _on_mode(self, state: ViewerState, event) -> None:
        setting = (self.mode.value, float(self.threshold.value))
        if (state.mode, state.threshold) != setting:
            state.set_mode(*setting)

    def _on_level(self, state: ViewerState, event) -> None:
        level = LEVEL_OPTIONS.index(self.level.value) + 1
        if level != state.level:
            state.set_level(level)

    def _on_colors(self, state: ViewerState, event) -> None:
        state.set_color(self.colors.value)

    def _client_camera(self, client, max_height: int | None = None):
        camera = client.camera
        width, height = int(camera.image_width), int(camera.image_height)
        if max_height is not None:
            width, height = viewport_size(width, height, max_height)
        return viewport_camera(camera.wxyz, camera.position, camera.fov, width, height)

    def _on_scene_click(self, event) -> None:
        with self._reporting(event.client):
            if self.state is None or not self.picking.value:
                return
            camera = self._client_camera(event.client)
            width, height = int(camera.widths[0]), int(camera.heights[0])
            pixel = click_pixel(event.screen_pos, width, height)
            if self.state.pick(camera, pixel) is None:
                self.report("nothing under the click", event.client)
                return
            self.refresh()

    def _on_mask(self, state: ViewerState, event) -> None:
        if event.client is None:
            raise ThgsError("the 2D mask needs a browser's view")
        view = state.view_mask(self._client_camera(event.client, self.config.mask_height))
        self.mask_image.image = view.picture
        self.mask_image.visible = True

    def _on_view(self, state: ViewerState, event) -> None:
        if self.views.value == "—" or self.scene is None or self.scene.cameras is None:
            return
        cameras = self.scene.cameras
        index = cameras.stems.index(self.views.value)
        target = np.asarray(self.server.initial_camera.look_at)
        distance = float(np.linalg.norm(cameras.centers()[index].numpy() - target))
        pose = camera_pose(cameras, index, max(distance, 1e-3))
        clients = [event.client] if event.client is not None else self.server.get_clients().values()
        for client in clients:
            with client.atomic():
                client.camera.wxyz = pose.wxyz
                client.camera.position = pose.position
                client.camera.look_at = pose.look_at
                client.camera.up_direction = pose.up
                client.camera.fov = pose.fov

    def export_target(self) -> Path:
        """The folder the "Folder" control names, resolved inside :attr:`export_root`.

        Raises:
            InputError: it resolves outside the export root (an absolute path elsewhere, ``..``,
                a link out).
        """
        folder = (self.export_root / self.export_folder.value.strip()).resolve()
        if folder != self.export_root and self.export_root not in folder.parents:
            raise InputError(
                "Export folder",
                f"{self.export_folder.value!r} is outside {self.export_root}; exports go inside "
                "the folder named when the viewer started (thgs view --export-root)",
            )
        return folder

    def _on_export(self, state: ViewerState, event) -> None:
        folder = self.export_target()
        paths = state.export(folder)
        self.problem = None
        self.export_result.content = f"wrote {', '.join(p.name for p in paths)} to `{folder}`"
        if event.client is not None:
            event.client.add_notification(
                "thgs", f"exported to {folder}", color="green", auto_close_seconds=5.0
            )

    def _on_open(self, event) -> None:
        with self._reporting(event.client):
            self.open(checked_field_file(self.field_path.value))

    # Drawing ------------------------------------------------------------------------------------

    def refresh(self) -> None:
        """Re-send the colours that changed and rewrite the panels from the state."""
        with self._lock:
            state = self.state
            if state is None:
                self._update_status()
                return
            rgb, opacity = state.colors()
            if self.splats is not None:
                self.splats.update(rgb, opacity)
            with self._synced():
                self.level.value = _level_option(state.level)
            self.results.content = self._results_markdown(state)
            self.hierarchy.content = self._hierarchy_markdown(state)
            self._update_status()

    def _update_status(self) -> None:
        lines = []
        if self.state is not None and self._field_path is not None:
            field = self.state.field
            counts = " / ".join(f"{n:,}" for n in field.region_counts[1:])
            lines.append(
                f"**{self._field_path.name}**: {len(field):,} Gaussians; "
                f"sub-parts / parts / objects {counts}"
            )
        else:
            lines.append("No field is open.")
        lines += [f"*{note}*" for note in [*self.notes, self.text_off] if note]
        if self.problem is not None:
            lines.append(f"**Problem:** {self.problem}")
        self.status.content = "  \n".join(lines)

    @staticmethod
    def _results_markdown(state: ViewerState) -> str:
        highlight = state.highlight
        if highlight is None or highlight.kind != "query":
            return ""
        count = int(highlight.gaussians.sum())
        if not highlight.regions:
            head = f"**{highlight.text}**: {highlight.reason or 'nothing relevant enough'}"
        else:
            plural = "s" if len(highlight.regions) > 1 else ""
            head = (
                f"**{highlight.text}**: {len(highlight.regions)} region{plural}, "
                f"{count:,} Gaussians"
            )
        if highlight.confidence is not None:
            head += f"  \nconfidence that the scene holds it: {highlight.confidence:.2f}"
        selected = {(level, region) for level, region, _ in highlight.regions}
        rows = []
        for level, region, score in _ranking_with_selection(highlight):
            confidence = highlight.region_confidence.get((level, region))
            rows.append(
                f"| {'✓' if (level, region) in selected else ''} | {LEVEL_NAMES[level]} {region} "
                f"| {score:.3f} | {'' if confidence is None else f'{confidence:.2f}'} "
                f"| {int(state.field.sizes(level)[region]):,} |"
            )
        table = [
            "| | region | relevancy | confidence | Gaussians |",
            "|---|---|---|---|---|",
            *rows,
        ]
        return "\n".join([head, "", *table])

    @staticmethod
    def _hierarchy_markdown(state: ViewerState) -> str:
        highlight = state.highlight
        if highlight is None or highlight.primary is None:
            return "Click on the scene to pick a region."
        level, region = highlight.primary
        chain = [f"{LEVEL_NAMES[level]} {region}"]
        for up in range(level, 3):
            region = state.field.parent(up, region)
            chain.append(f"{LEVEL_NAMES[up + 1]} {region}")
        size = int(state.field.sizes(highlight.primary[0])[highlight.primary[1]])
        children = len(state.field.children(*highlight.primary)) if highlight.primary[0] > 1 else 0
        return (
            f"Selected: **{chain[0]}** ({size:,} Gaussians"
            + (f", {children} children" if children else "")
            + ")  \nin "
            + " ⊂ ".join(chain[1:] or ["the scene"])
        )


def _ranking_with_selection(highlight: Highlight) -> list[tuple[int, int, float]]:
    """The query's ranking, followed by any selected region outside it (the paper's mode pools
    another level)."""
    rows = list(highlight.ranking)
    listed = {(level, region) for level, region, _ in rows}
    rows += [
        (level, region, float(score))
        for level, region, score in highlight.regions
        if (level, region) not in listed and score is not None
    ]
    return rows


def start_viewer(
    field: str | os.PathLike[str],
    *,
    scene: str | os.PathLike[str] | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    text_model: str | os.PathLike[str] | None = None,
    config: ViewerConfig = ViewerConfig(),
    device: str = "auto",
    token: bool = True,
    export_root: str | os.PathLike[str] | None = None,
) -> ViewerApp:
    """Start a viser server on ``host``:``port`` and show ``field`` in it.

    The server answers only requests addressed to it (``Host`` and ``Origin``) and, with
    ``token`` (the default), carrying the secret made here (``app.token``; in
    :func:`viewer_url`): :mod:`thgs.viewer.guard`. ``token=False`` is the explicit opt-out.
    Exports are confined to ``export_root`` (default ``./thgs-export``).

    The server always starts: a field that cannot be opened (unreadable, or built on other
    Gaussians than the scene) is reported in ``app.problem``, in the log and in the viewer, where
    another field can be opened. If ``port`` is taken, the next free port is used and
    ``app.notes`` says so; ``app.url`` is where the viewer is.

    Returns:
        the running app; ``app.stop()`` stops it.

    Raises:
        ThgsError: viser is not installed (``pip install 'thgs[viewer]'``).
        InputError: ``export_root`` exists and is not a folder (before the server starts).
    """
    try:
        import viser
    except ImportError as error:
        raise ThgsError("the viewer needs viser: pip install 'thgs[viewer]'") from error
    if export_root is not None and Path(export_root).exists() and not Path(export_root).is_dir():
        raise InputError(
            export_root, "is a file; the export root is the folder exports go into (--export-root)"
        )

    guard = AccessGuard(host, new_token() if token else None)
    # viser prints a banner (the CLI prints instead)
    with contextlib.redirect_stdout(io.StringIO()), guarded_websockets(guard):
        server = viser.ViserServer(host=host, port=port, label="thgs", verbose=False)
    app = ViewerApp(
        server,
        config,
        scene=scene,
        text_model=text_model,
        device=device,
        export_root=export_root,
    )
    app.token = guard.token
    bound = server.get_port()
    if port != 0 and bound != port:
        app.notes.append(f"port {port} is in use; serving on port {bound}")
        logger.warning("port %d is in use; serving on port %d", port, bound)
    try:
        app.open(field)
    except ThgsError as error:
        app.field_path.value = str(field)
        app.report(str(error))
    return app


def checked_field_file(value: str) -> Path:
    """The path the "Open field" control names, if it is a readable field file.

    Whatever is wrong with a path that is not a field (missing, unreadable, a folder, another
    kind of file) gets the same answer, so the control tells nothing about other files.

    Raises:
        InputError: not a ``.thgs`` file that reads as a field.
    """
    path = Path(value.strip()).expanduser()
    refusal = InputError(path, "is not a readable field file (.thgs)")
    if path.suffix != ".thgs":
        raise refusal
    try:
        load_field(path)
    except (ThgsError, OSError, ValueError):
        raise refusal from None
    return path


def viewer_url(app: ViewerApp, host: str) -> str:
    """The address to open in a browser, with the token when the server needs one."""
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    shown = f"[{shown}]" if ":" in shown else shown
    query = f"/?token={app.token}" if app.token is not None else ""
    return f"http://{shown}:{app.server.get_port()}{query}"
