"""The browser viewer of a run: a viser server fed from the run folder.

:class:`RunViewer` watches a run folder (:class:`~edgerecon.viewer.rundir.RunFolder`) on its
own thread and shows, in any browser that opens its URL:

* the newest merged cloud, decimated to ``ViewerConfig.point_budget`` points, in one of the
  colourings of :mod:`edgerecon.viewer.colors` (a menu offers those the cloud supports);
* the rig's cameras as frusta, the task's chosen subset pi(N') highlighted (orange);
* a panel with the task's time index, r, N', latency against the deadline, online (and,
  on synthetic scenes, offline) F-score, background version and degraded / failed state;
* a chart of latency, deadline and quality over the newest tasks (``chart_tasks``);
* a task slider that replays finished tasks ("follow live" returns to the newest).

It never talks to the running session: it reads the files the session writes atomically, so
it works for finished and running runs and for both engines. Only the newest task is drawn
when several arrived since the last look (older ones are skipped and counted), and viser's
outgoing buffer keeps only the newest cloud for a client that is slow to receive, so a
slow network or browser never builds a backlog. Lengths are shown in metres (the rig's unit
converted) with the rig's ``up`` as the scene's up direction.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.geometry.camera import Rig
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.types import PointCloud
from edgerecon.viewer.colors import (
    COLORINGS,
    available_colorings,
    colorize,
    decimate,
    point_spacing,
    unit_to_metres,
)
from edgerecon.viewer.layout import initial_view, task_panel, timeline
from edgerecon.viewer.rundir import RunFolder

logger = logging.getLogger(__name__)

#: Colours of the camera frusta.
CHOSEN_RGB = (255, 120, 0)
IDLE_RGB = (120, 120, 120)


@dataclass(frozen=True, kw_only=True)
class ViewerConfig:
    """Settings of the run viewer."""

    host: str = "127.0.0.1"
    """Interface the HTTP/WebSocket server binds (127.0.0.1: this machine only)."""
    port: int = 8080
    """TCP port; 0 = any free port (``RunViewer.port`` tells which)."""
    point_budget: int = 150_000
    """Most points drawn per cloud (the foreground keeps at least half of them)."""
    poll_s: float = 0.25
    """How often the run folder is checked for new tasks, seconds."""
    coloring: str = "rgb"
    """Initial colouring (a key of ``viewer.colors.COLORINGS``)."""
    point_size_m: float | None = None
    """Drawn point size in metres; None = 1.5 x the first cloud's median point spacing."""
    chart_tasks: int = 1000
    """The chart shows the newest this many tasks (every update sends its data to every
    client: a live run of hours would send ever more; the slider reaches every task)."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"ViewerConfig.port must be in 0..65535, got {self.port}")
        if self.point_budget < 1:
            raise ValueError(f"ViewerConfig.point_budget must be >= 1, got {self.point_budget}")
        if not self.poll_s > 0:
            raise ValueError(f"ViewerConfig.poll_s must be > 0, got {self.poll_s}")
        if self.coloring not in COLORINGS:
            raise ValueError(
                f"ViewerConfig.coloring must be one of {list(COLORINGS)}, got {self.coloring!r}"
            )
        if self.chart_tasks < 2:
            raise ValueError(f"ViewerConfig.chart_tasks must be >= 2, got {self.chart_tasks}")
        if self.point_size_m is not None and not self.point_size_m > 0:
            raise ValueError(f"ViewerConfig.point_size_m must be > 0, got {self.point_size_m}")


def viser_available() -> bool:
    """Whether the viewer's library is installed (the ``[viewer]`` extra)."""
    import importlib.util

    return importlib.util.find_spec("viser") is not None


def require_viser() -> None:
    if not viser_available():
        from edgerecon.types import EdgereconError

        raise EdgereconError(
            "the viewer needs viser: pip install 'edgerecon[viewer]' (or '.[viewer]' in a checkout)"
        )


class RunViewer:
    """Serve a run folder in the browser (see module docstring).

    ``start()`` binds the server and starts the watcher thread; ``stop()`` ends both.
    ``refresh()`` runs one watcher step (what the thread does every ``poll_s``).
    """

    def __init__(self, run_dir: str | os.PathLike[str], config: ViewerConfig | None = None):
        self.config = config or ViewerConfig()
        self.run = RunFolder(run_dir)
        self.stats = {"tasks_seen": 0, "clouds_sent": 0, "clouds_skipped": 0}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._rig: Rig | None = None
        self._to_m = 1.0
        self._shown: TaskMetrics | None = None
        self._cloud: PointCloud | None = None  # decimated, in metres
        self._num_points = 0
        self._point_size: float | None = self.config.point_size_m
        self._frusta: list[Any] = []
        self._gui: dict[str, Any] = {}
        self._updating_slider = False

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> RunViewer:
        require_viser()
        import viser

        with _quiet():  # viser prints a banner on stdout, which belongs to --json output
            self._server = viser.ViserServer(
                host=self.config.host, port=self.config.port, label="edgerecon", verbose=False
            )
        self._server.scene.world_axes.visible = False
        self._build_gui()
        self.refresh()
        self._thread = threading.Thread(target=self._watch, name="edgerecon-viewer", daemon=True)
        self._thread.start()
        return self

    @property
    def port(self) -> int:
        return int(self._server.get_port()) if self._server is not None else self.config.port

    @property
    def url(self) -> str:
        host = self.config.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{self.port}"

    @property
    def server(self) -> Any:
        """The underlying ``viser.ViserServer`` (None before ``start``)."""
        return self._server

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._server is not None:
            with _quiet():
                self._server.stop()
            self._server = None

    def serve_forever(self, parent_pid: int | None = None) -> None:
        """Block until interrupted (or until process ``parent_pid`` is gone)."""
        from edgerecon.runtime.memory import start_heap_trimmer

        start_heap_trimmer()  # the viewer lives as long as a live run (runtime.memory)
        try:
            while not self._stop.wait(1.0):
                if parent_pid is not None and not _alive(parent_pid):
                    logger.info("viewer: the run's process %d ended", parent_pid)
                    break
        finally:
            self.stop()

    def __enter__(self) -> RunViewer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ watching
    def _watch(self) -> None:
        while not self._stop.wait(self.config.poll_s):
            try:
                self.refresh()
            except Exception:  # the viewer must outlive any bad file it meets
                logger.exception("viewer: refresh failed")

    def refresh(self) -> int:
        """Read new tasks; draw the newest one when following live. Returns the number of
        new tasks."""
        with self._lock:
            resets = self.run.resets
            new = self.run.poll()
            if self.run.resets != resets:
                self._shown = None
            rig = self.run.rig()
            if rig is not None and rig is not self._rig:  # the first, or placed again
                self._set_rig(rig)
            if not new and self._shown is not None:
                self._update_status()
                return 0
            self.stats["tasks_seen"] += len(new)
            self._update_timeline()
            if self._follow():
                target = self.run.newest_with_cloud()
                if target is not None and (self._shown is None or target.task != self._shown.task):
                    skipped = sum(1 for m in new if m.status == "ok" and m.task != target.task)
                    self.stats["clouds_skipped"] += skipped
                    self._show(target)
            self._update_status()
            return len(new)

    def _follow(self) -> bool:
        box = self._gui.get("follow")
        return True if box is None else bool(box.value)

    # ------------------------------------------------------------------ scene
    def _set_rig(self, rig: Rig) -> None:
        self._rig = rig
        self._to_m = unit_to_metres(rig.unit)
        server = self._server
        server.scene.set_up_direction(tuple(float(v) for v in rig.up))
        scale = rig.scene_scale() * self._to_m
        view = initial_view(rig)
        server.initial_camera.fov = math.radians(view.fov_deg)
        server.initial_camera.position = tuple(view.position)
        server.initial_camera.look_at = tuple(view.look_at)
        server.initial_camera.up = tuple(view.up)
        import viser.transforms as vtf

        self._frusta = []
        for cam in rig:
            fov = 2 * math.atan2(cam.height / 2, cam.K[1, 1])
            handle = server.scene.add_camera_frustum(
                f"/cameras/{cam.name}",
                fov=fov,
                aspect=cam.width / cam.height,
                scale=0.06 * scale,
                thickness=0.0025 * scale,
                color=IDLE_RGB,
                wxyz=vtf.SO3.from_matrix(cam.R.T).wxyz,
                position=tuple(cam.center * self._to_m),
            )
            self._frusta.append(handle)

    def _show(self, m: TaskMetrics) -> bool:
        cloud = self.run.cloud(m.time_index)
        if cloud is None:
            return False
        self._num_points = len(cloud)
        cloud = cloud.select(decimate(cloud, self.config.point_budget))
        cloud = PointCloud(
            points3D=cloud.points3D * self._to_m,
            colors=cloud.colors,
            labels=cloud.labels,
            attributes=cloud.attributes,
        )
        self._cloud = cloud
        self._shown = m
        if self._point_size is None and len(cloud) > 1:
            self._point_size = 1.5 * point_spacing(cloud.points3D)
        options = available_colorings(cloud)
        menu = self._gui["coloring"]
        labels = tuple(COLORINGS[k] for k in options)
        if tuple(menu.options) != labels:
            current = menu.value
            menu.options = labels
            menu.value = current if current in labels else COLORINGS["rgb"]
        self._draw()
        chosen = set(m.camera_ids)
        for i, frustum in enumerate(self._frusta):
            frustum.color = CHOSEN_RGB if i in chosen else IDLE_RGB
        self._select_slider(m.task)
        self.stats["clouds_sent"] += 1
        return True

    def _coloring_key(self) -> str:
        label = self._gui["coloring"].value
        return next((k for k, v in COLORINGS.items() if v == label), "rgb")

    def _draw(self) -> None:
        cloud = self._cloud
        if cloud is None or self._server is None:
            return
        size = (self._point_size or 0.01) * float(self._gui["point_size"].value)
        self._server.scene.add_point_cloud(
            "/cloud",
            points=cloud.points3D.astype(np.float32),
            colors=colorize(cloud, self._coloring_key()),
            point_size=max(size, 1e-4),
            point_shape="circle",
            precision="float32",
            point_shading="flat",
        )

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui = self._server.gui
        g = self._gui
        g["status"] = gui.add_markdown("waiting for the run's first task ...")
        g["task"] = gui.add_markdown("")
        g["chart"] = gui.add_uplot(
            data=(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)),
            series=(
                {"label": "task"},
                {"label": "latency (s)", "stroke": "#1f77b4", "width": 2, "scale": "s"},
                {"label": "deadline (s)", "stroke": "#d62728", "dash": [6, 4], "scale": "s"},
                {"label": "F online", "stroke": "#2ca02c", "scale": "F"},
                {"label": "F offline", "stroke": "#9467bd", "scale": "F"},
            ),
            scales={"x": {"time": False}, "s": {"auto": True}, "F": {"range": [0, 1]}},
            axes=({}, {"scale": "s", "label": "s"}, {"scale": "F", "side": 1, "label": "F"}),
            title="latency and quality per task",
            aspect=1.6,
        )
        with gui.add_folder("Replay"):
            g["follow"] = gui.add_checkbox("follow live", initial_value=True)
            g["slider"] = gui.add_slider("task", min=0, max=1, step=1, initial_value=0)
        with gui.add_folder("Display"):
            g["coloring"] = gui.add_dropdown(
                "colour by",
                options=tuple(COLORINGS[k] for k in ("rgb",)),
                initial_value=COLORINGS["rgb"],
            )
            g["point_size"] = gui.add_slider(
                "point size", min=0.25, max=4.0, step=0.25, initial_value=1.0
            )
            g["cameras"] = gui.add_checkbox("cameras", initial_value=True)
        if self.config.coloring != "rgb":
            g["coloring"].options = (COLORINGS["rgb"], COLORINGS[self.config.coloring])
            g["coloring"].value = COLORINGS[self.config.coloring]

        @g["coloring"].on_update
        def _(_: Any) -> None:
            with self._lock:
                self._draw()

        @g["point_size"].on_update
        def _(_: Any) -> None:
            with self._lock:
                self._draw()

        @g["cameras"].on_update
        def _(_: Any) -> None:
            for f in self._frusta:
                f.visible = bool(g["cameras"].value)

        @g["slider"].on_update
        def _(_: Any) -> None:
            if self._updating_slider:
                return
            with self._lock:
                g["follow"].value = False
                self.replay(int(g["slider"].value))

        @g["follow"].on_update
        def _(_: Any) -> None:
            if g["follow"].value:
                with self._lock:
                    target = self.run.newest_with_cloud()
                    if target is not None:
                        self._show(target)
                    self._update_status()

    def replay(self, task_position: int) -> bool:
        """Show the task at ``task_position`` in the run's list (or the newest one with a
        cloud before it)."""
        with self._lock:
            m = self.run.newest_with_cloud(task_position)
            if m is None:
                return False
            ok = self._show(m)
            self._update_status()
            return ok

    def _select_slider(self, task: int) -> None:
        slider = self._gui["slider"]
        pos = next((i for i, m in enumerate(self.run.tasks) if m.task == task), None)
        if pos is not None and slider.value != pos:
            self._updating_slider = True
            try:
                slider.value = pos
            finally:
                self._updating_slider = False

    def _update_timeline(self) -> None:
        tasks = self.run.tasks
        if not tasks:
            return
        x, lat, dl, fon, foff = timeline(tasks[-self.config.chart_tasks :])
        self._gui["chart"].data = (x, lat, dl, fon, foff)
        slider = self._gui["slider"]
        slider.max = max(1, len(tasks) - 1)
        slider.disabled = len(tasks) < 2

    def _update_status(self) -> None:
        tasks = self.run.tasks
        state = "finished" if self.run.finished else "running"
        if not tasks:
            text = f"**{self.run.path.name}**: waiting for the first task ..."
        else:
            failed = sum(m.status != "ok" for m in tasks)
            degraded = sum(m.degraded for m in tasks if m.status == "ok")
            rss = tasks[-1].rss_mb
            text = (
                f"**{self.run.path.name}**: {state}, {len(tasks)} tasks"
                f" ({failed} failed, {degraded} degraded)"
                + ("" if rss is None else f", memory {rss:,.0f} MB")
                + ("" if self._follow() else " · replaying")
            )
        self._set_text("status", text)
        if self._shown is not None:
            newest = tasks[-1] if tasks else self._shown
            self._set_text(
                "task",
                task_panel(
                    self._shown, self._rig, self._num_points, len(self._cloud or ()), newest
                ),
            )

    def _set_text(self, name: str, text: str) -> None:
        # Every assignment is a message to every client: send changes only.
        handle = self._gui[name]
        if handle.content != text:
            handle.content = text


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def serve_run(run_dir: str | os.PathLike[str], config: ViewerConfig | None = None) -> RunViewer:
    """Start a viewer on ``run_dir`` (which may not exist yet: a run about to start)."""
    return RunViewer(Path(run_dir), config).start()
