"""Draw episodes of the intersection: a planner on a scenario as a GIF, an MP4 or an HTML animation.

One frame per policy step, drawn with matplotlib from the simulation's arrays (the scene of every
step) and the layout's geometry (its routes and conflict zones); no display, no pygame. A frame
shows the simulated time, the planner, the conflict zones and every vehicle coloured by its state:

- *moving*; *stopped* (speed below :data:`envs.simulation.scene.STOP_SPEED`);
- *governor held*: the simulation's speed governor lowered the planner's command in that step
  (``StepRecord.governed``);
- *shield overrode*: the safety shield replaced the planner's command in that step (a shielded
  planner's ``last_overridden``);
- *collided*: the vehicles of a collision in that step, drawn where they were when it happened
  (the harness removes them from the scene) for :data:`COLLIDED_SHOWN_S` seconds.

:class:`EpisodeRecorder` keeps the frames of a run (:func:`envs.evaluation.recording.record_episode` runs
the evaluation harness's loop with it, so that a recorded run is the run of the report);
:func:`write_animation` draws one or several recorded episodes side by side (the same scenario under
different planners).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import animation  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from envs.simulation.layouts import LANE_WIDTH  # noqa: E402
from envs.simulation.scene import STOP_SPEED, Scene  # noqa: E402
from envs.simulation.step_record import StepRecord  # noqa: E402

MOVING, STOPPED, GOVERNED, SHIELDED, COLLIDED = range(5)
#: state -> (legend label, colour); a vehicle in several states shows the highest one
STATES = (
    ("moving", "#1f77b4"),
    (f"stopped (< {STOP_SPEED} m/s)", "#ff7f0e"),
    ("governor held", "#9467bd"),
    ("shield overrode", "#d62728"),
    ("collided", "#000000"),
)
ZONE_COLOR = "#e6b800"
ROAD_COLOR = "#d9d9d9"
#: how long the vehicles of a collision stay drawn after it [s]
COLLIDED_SHOWN_S = 2.0
#: output suffix -> what writes it
FORMATS = (".gif", ".mp4", ".html")
# matplotlib's HTML player draws its buttons with font-awesome icons loaded from a CDN; a self-contained
# file shows the same buttons as Unicode glyphs instead (icon class -> glyph).
HTML_ICONS = {
    "fa fa-minus": "\u2212", "fa fa-fast-backward": "\u23ee", "fa fa-step-backward": "\u25c1",
    "fa fa-play fa-flip-horizontal": "\u25c0", "fa fa-pause": "\u23f8", "fa fa-play": "\u25b6",
    "fa fa-step-forward": "\u25b7", "fa fa-fast-forward": "\u23ed", "fa fa-plus": "+",
}  # fmt: skip
DEFAULT_WIDTH = 2.0  # [m], a scene without widths (as Scene.width says)


@dataclass
class Frame:
    """Every vehicle at the end of one policy step.

    :param time: simulated time [s]
    :param corners: ``(n, 4, 2)`` the vehicles' body outlines [m]
    :param state: ``(n,)`` int, one of ``MOVING`` ... ``COLLIDED``
    :param crossed: vehicles that crossed so far
    :param collided: vehicles that collided so far
    :param in_scene: vehicles in the scene
    """

    time: float
    corners: np.ndarray
    state: np.ndarray
    crossed: int
    collided: int
    in_scene: int


@dataclass
class Episode:
    """One planner's recorded run.

    :param name: the planner's report name (the panel's title)
    :param layout: the intersection (:class:`envs.simulation.layouts.Layout`)
    :param frames: one :class:`Frame` per policy step
    :param facts: :func:`envs.evaluation.harness.run_episode`'s facts, and ``crossed``, ``collided``
    """

    name: str
    layout: Any
    frames: list[Frame] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)


def outlines(position: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Body rectangles of vehicles.

    :param position: ``(n, 2)`` centres [m]
    :param heading: ``(n,)`` [rad]
    :param length: ``(n,)`` [m]
    :param width: ``(n,)`` [m]
    :return: ``(n, 4, 2)`` corners, counter-clockwise
    """
    forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    left = np.stack([-forward[:, 1], forward[:, 0]], axis=-1)
    half_l = (np.asarray(length, float) / 2)[:, None]
    half_w = (np.asarray(width, float) / 2)[:, None]
    corners = [
        position + forward * half_l + left * half_w,
        position - forward * half_l + left * half_w,
        position - forward * half_l - left * half_w,
        position + forward * half_l - left * half_w,
    ]
    return np.stack(corners, axis=1)


def _scene_outlines(scene: Scene, rows: np.ndarray | None = None) -> np.ndarray:
    rows = np.arange(scene.num_vehicles) if rows is None else rows
    width = scene.width[rows] if scene.width is not None else np.full(len(rows), DEFAULT_WIDTH)
    return outlines(scene.position[rows], scene.heading[rows], scene.length[rows], width)


class EpisodeRecorder:
    """The ``on_step`` of :func:`envs.evaluation.harness.run_episode` that keeps one :class:`Frame` per step.

    :param planner: the planner that drives the run (a shielded one reports the vehicles it overrode)
    :param tick: called once per step (a progress bar's ``update``)
    """

    def __init__(self, planner, tick: Callable[[], Any] | None = None) -> None:
        self.planner = planner
        self.tick = tick
        self.frames: list[Frame] = []
        self.crossed = 0
        self.collided = 0
        self._wrecks: list[tuple[float, np.ndarray]] = []  # (time of the collision, outlines)

    def __call__(self, scene: Scene, acc: np.ndarray, record: StepRecord, next_scene: Scene) -> None:
        now = float(record.time)
        ids = next_scene.vehicle_id
        state = np.where(next_scene.speed < STOP_SPEED, STOPPED, MOVING)
        state[np.isin(ids, record.governed)] = GOVERNED
        overridden = getattr(self.planner, "last_overridden", None)  # the shield's own record of this step
        if overridden is not None and len(overridden) == scene.num_vehicles:
            state[np.isin(ids, scene.vehicle_id[np.asarray(overridden, bool)])] = SHIELDED
        collided = record.collided
        corners = _scene_outlines(next_scene)
        if len(collided):
            self.collided += len(collided)
            gone = np.isin(scene.vehicle_id, collided) & ~np.isin(scene.vehicle_id, ids)
            if gone.any():  # removed by the harness: draw them where they were at the step's start
                self._wrecks.append((now, _scene_outlines(scene, np.flatnonzero(gone))))
            state[np.isin(ids, collided)] = COLLIDED
        self.crossed += len(record.crossed)
        self._wrecks = [(t, c) for t, c in self._wrecks if now - t < COLLIDED_SHOWN_S - 1e-9]
        if self._wrecks:
            wrecks = np.concatenate([c for _, c in self._wrecks])
            corners = np.concatenate([corners, wrecks])
            state = np.concatenate([state, np.full(len(wrecks), COLLIDED)])
        frame = Frame(now, corners, state.astype(np.int64), self.crossed, self.collided, next_scene.num_vehicles)
        self.frames.append(frame)
        if self.tick is not None:
            self.tick()


def _band(xy: np.ndarray, half_width: float) -> np.ndarray:
    """The outline of a strip ``half_width`` either side of a polyline ``(m, 2)``: ``(2m, 2)``."""
    d = np.gradient(xy, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1) * half_width
    return np.concatenate([xy + normal, (xy - normal)[::-1]])


def _route_samples(layout, route: int) -> np.ndarray:
    """The samples of a route's centre line without the padding (repeats of its last sample)."""
    count = int(np.floor(layout.length[route] / layout.ds)) + 1
    return layout.xy[route, : min(count, layout.xy.shape[1])]


def zone_outlines(layout, half_width: float = 1.0) -> list[np.ndarray]:
    """The conflict zones as polygons: on each route, the stretches of its centre line that lie in a
    zone with a conflicting route (:attr:`envs.simulation.layouts.Layout.zone_start`), ``half_width`` either side.

    :param layout: the intersection
    :param half_width: half the drawn width [m] (a vehicle's half width)
    :return: one ``(k, 2)`` polygon per stretch
    """
    polygons = []
    for route in range(layout.num_routes):
        xy = _route_samples(layout, route)
        arc = np.arange(len(xy)) * layout.ds
        inside = np.zeros(len(xy), bool)
        for other in np.flatnonzero(layout.conflicts[route]):
            lo, hi = layout.zone_start[route, other], layout.zone_end[route, other]
            if np.isfinite(lo) and np.isfinite(hi):
                inside |= (arc >= lo) & (arc <= hi)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(np.int8), [0]])))
        for start, stop in zip(edges[::2], edges[1::2]):
            if stop - start >= 2:
                polygons.append(_band(xy[start:stop], half_width))
    return polygons


def _draw_background(ax, layout, view: float) -> None:
    roads = [_band(_route_samples(layout, r), LANE_WIDTH / 2) for r in range(layout.num_routes)]
    ax.add_collection(PolyCollection(roads, facecolors=ROAD_COLOR, edgecolors="none", zorder=0))
    ax.add_collection(
        PolyCollection(zone_outlines(layout), facecolors=ZONE_COLOR, edgecolors="none", alpha=0.35, zorder=1)
    )
    xy = np.concatenate([_route_samples(layout, r) for r in range(layout.num_routes)])
    low, high = np.maximum(xy.min(axis=0), -view) - LANE_WIDTH, np.minimum(xy.max(axis=0), view) + LANE_WIDTH
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(high[1], low[1])  # y points down, as in highway-env's frame: the south arm at the bottom
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_facecolor("#f4f7f0")


def _figure(episodes: Sequence[Episode], panel_inches: float, view: float = 50.0):
    """The figure, one panel per episode (up to 3 a row), with the legend under them."""
    columns = min(len(episodes), 3)
    rows = int(np.ceil(len(episodes) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(panel_inches * columns, panel_inches * rows + 0.55), squeeze=False)
    panels = []
    colors = np.array([color for _, color in STATES])
    for ax, episode in zip(axes.ravel(), episodes):
        _draw_background(ax, episode.layout, view)
        ax.set_title(episode.name, fontsize=9)
        vehicles = PolyCollection([], edgecolors="white", linewidths=0.3, zorder=3)
        ax.add_collection(vehicles)
        clock = ax.text(0.02, 0.98, "", transform=ax.transAxes, va="top", ha="left", fontsize=8, family="monospace")
        panels.append((episode, vehicles, clock))
    for ax in axes.ravel()[len(episodes):]:
        ax.set_visible(False)
    handles = [Patch(color=color, label=label) for label, color in STATES]
    handles.append(Patch(color=ZONE_COLOR, alpha=0.35, label="conflict zone"))
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.subplots_adjust(left=0.01, right=0.99, top=1 - 0.3 / (panel_inches * rows + 0.55),
                        bottom=0.5 / (panel_inches * rows + 0.55), wspace=0.03, hspace=0.1)  # fmt: skip

    def draw(k: int):
        artists = []
        for episode, vehicles, clock in panels:
            frame = episode.frames[min(k, len(episode.frames) - 1)]
            vehicles.set_verts(list(frame.corners))
            vehicles.set_facecolors(colors[frame.state] if len(frame.state) else [])
            clock.set_text(
                f"t = {frame.time:5.1f} s\nin scene {frame.in_scene:3d}\n"
                f"crossed {frame.crossed:4d}\ncollided {frame.collided:3d}"
            )
            artists += [vehicles, clock]
        return artists

    return fig, draw


def check_format(path: str | Path) -> str:
    """The output format of ``path`` (its suffix), checked; an MP4 needs an ffmpeg encoder.

    :raises ValueError: an unknown suffix, or ``.mp4`` without ffmpeg (naming the extra to install)
    """
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"must end in {', '.join(FORMATS)}, got {str(path)!r}")
    if suffix == ".mp4" and ffmpeg_path() is None:
        raise ValueError("an .mp4 needs an ffmpeg encoder: pip install 'sb3-graph[video]' (imageio-ffmpeg), or "
                         "ffmpeg on the PATH; .gif and .html need none")  # fmt: skip
    return suffix


def ffmpeg_path() -> str | None:
    """An ffmpeg executable: imageio-ffmpeg's (the ``video`` extra), else one on the PATH."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return shutil.which("ffmpeg")


def write_animation(
    episodes: Sequence[Episode],
    path: str | Path,
    fps: float,
    dpi: int = 80,
    panel_inches: float = 5.0,
    progress: Callable[[int, int], Any] | None = None,
    view: float = 50.0,
    file_format: str | None = None,
) -> int:
    """Draw recorded episodes side by side, one frame per policy step, into a GIF, MP4 or HTML file.

    :param episodes: the episodes (all with the same number of frames, as runs of one duration)
    :param path: the file to write; its suffix (:data:`FORMATS`) chooses the format: ``.gif`` (Pillow),
        ``.mp4`` (ffmpeg, see :func:`ffmpeg_path`), ``.html`` (self-contained, frames embedded)
    :param fps: frames per second of the animation (the policy frequency plays it in real time)
    :param dpi: pixels per inch
    :param panel_inches: size of one panel [in]
    :param progress: ``progress(frame, total)`` while the frames are drawn
    :param view: half-width of the drawn area around the intersection's centre [m]
    :param file_format: ``".gif"``, ``".mp4"`` or ``".html"`` instead of ``path``'s suffix (e.g. for a
        temporary file)
    :return: the number of frames written
    """
    if not episodes or not all(e.frames for e in episodes):
        raise ValueError("nothing to draw: an episode has no frame (a duration shorter than one policy step?)")
    suffix = check_format(path if file_format is None else Path(f"episode{file_format}"))
    total = max(len(e.frames) for e in episodes)
    fig, draw = _figure(episodes, panel_inches, view)
    movie = animation.FuncAnimation(fig, draw, frames=total, blit=False, repeat=False, cache_frame_data=False)
    if suffix == ".gif":
        writer = animation.PillowWriter(fps=fps)
    elif suffix == ".mp4":
        matplotlib.rcParams["animation.ffmpeg_path"] = ffmpeg_path()
        writer = animation.FFMpegWriter(  # x264 needs even sizes
            fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"]
        )
    else:
        writer = animation.HTMLWriter(fps=fps, embed_frames=True, default_mode="once")
    callback = (lambda i, n: progress(i + 1, n)) if progress is not None else None
    path = Path(path)
    # The writers choose by suffix and some write side files: draw into a private folder, then move.
    with tempfile.TemporaryDirectory(prefix=".record-", dir=path.parent) as folder:
        target = Path(folder) / f"episode{suffix}"
        with matplotlib.rc_context({"animation.embed_limit": 1024.0}):  # MB: a long HTML episode
            movie.save(str(target), writer=writer, dpi=dpi, progress_callback=callback)
        plt.close(fig)
        if suffix == ".html":
            target.write_text(offline_html(target.read_text(encoding="utf-8")), encoding="utf-8")
        os.replace(target, path)
    return total


def offline_html(text: str) -> str:
    """matplotlib's HTML animation without its one remote resource: the font-awesome stylesheet (a CDN link)
    goes, and the buttons' icons become Unicode glyphs (:data:`HTML_ICONS`), so that the file loads nothing.

    :param text: the HTML that ``animation.HTMLWriter`` wrote
    :return: the same page, self-contained
    """
    import re

    text = re.sub(r"<link[^>]*font-awesome[^>]*>\s*", "", text, count=1)
    return re.sub(
        r'<i class="(fa [^"]+)"></i>', lambda m: HTML_ICONS.get(m.group(1), m.group(1).split("fa-")[-1]), text
    )


def write_frame(episodes: Sequence[Episode], path: str | Path, index: int, dpi: int = 100,
                panel_inches: float = 5.0, view: float = 50.0) -> None:  # fmt: skip
    """One frame as a still image (PNG), e.g. for a README.

    :param episodes: the recorded episodes
    :param path: the PNG file
    :param index: the frame (policy step) to draw
    :param dpi: pixels per inch
    :param panel_inches: size of one panel [in]
    :param view: half-width of the drawn area [m]
    """
    fig, draw = _figure(episodes, panel_inches, view)
    draw(index)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
