"""The merge seen from above: the drawing ``idas-sumo replay`` animates and the environments' ``rgb_array``.

Colours follow the route file's: a controlled car by the road it starts on, shaded by its driver type; a
SUMO-driven one grey. matplotlib is imported only when something is drawn.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from idas_sumo.env.rewards import MERGE_ZONE_RADIUS_M
from idas_sumo.env.snapshot import ROAD_NAMES
from idas_sumo.errors import InputError
from idas_sumo.sim.backend import has_display
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import NetParams

if TYPE_CHECKING:
    from idas_sumo.env.engine import MergeEngine

RENDER_MODES = ("rgb_array", "human")
"""The environments' render modes: frames of this drawing, or sumo-gui showing every step."""


def checked_render_mode(mode: str | None) -> str | None:
    """``mode`` if the environments know it and this machine can show it (``"human"`` needs a display)."""
    if mode is not None and mode not in RENDER_MODES:
        raise ValueError(f"render_mode {mode!r}: one of {', '.join(RENDER_MODES)}, or None")
    if mode == "human" and not has_display():
        raise InputError('render_mode "human" opens sumo-gui, which needs a display (DISPLAY is not set)')
    return mode


ROBOT_COLOUR = (150, 150, 150)
"""SUMO-driven (robot) cars: grey, as in the route file's vType."""
ROAD_COLOURS: dict[str, tuple[tuple[int, int, int], tuple[int, int, int]]] = {
    # (b_type = -2, least cooperative; b_type = +2, most): dark to light, blues and oranges.
    "main": ((8, 48, 107), (158, 202, 225)),
    "merge": ((127, 39, 4), (253, 174, 107)),
}
"""A controlled car's colour, by the road it starts on, shaded by its driver type."""
ZONE_COLOUR = "#9ecae1"
"""The merging zone's shade (the evaluation plots' too)."""
FRAME_SIZE_IN = (6.4, 3.2)
FRAME_DPI = 100
"""An ``rgb_array`` frame is 320 x 640 pixels (height x width), whatever the net."""


def vehicle_colour(road: str, b_type: float, controlled: bool) -> tuple[int, int, int]:
    """RGB (0-255) of a car: grey if SUMO drives it, else its start road's hue shaded by its driver type."""
    if not controlled:
        return ROBOT_COLOUR
    dark, light = ROAD_COLOURS[road]
    w = min(max((b_type + 2.0) / 4.0, 0.0), 1.0)
    return (
        round(dark[0] + w * (light[0] - dark[0])),
        round(dark[1] + w * (light[1] - dark[1])),
        round(dark[2] + w * (light[2] - dark[2])),
    )


def view_xy(road: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions in the view from above: the main road and the outgoing road along x, the merge road
    joining from below at the generated net's default angle (a sketch: the net's own shape is not read)."""
    angle = np.radians(NetParams().angle_deg)
    on_merge = road == "merge"
    x = np.where(on_merge, -dist * np.cos(angle), -dist)
    y = np.where(on_merge, -dist * np.sin(angle), 0.0)
    return x, y


def draw_roads(top: Any, site: MergeSite) -> None:
    """The still part of the view from above on the axes ``top``: the roads, the merging zone, labels."""
    from matplotlib.patches import Circle

    angle = np.radians(NetParams().angle_deg)
    main_len, merge_len = site.main.length_m, site.merge.length_m
    out_len = sum(lane.length_m for lane in site.out)
    road_style = {"color": "0.8", "lw": 6, "solid_capstyle": "butt", "zorder": 0}
    top.plot([-main_len, out_len], [0, 0], **road_style)
    top.plot([-merge_len * np.cos(angle), 0], [-merge_len * np.sin(angle), 0], **road_style)
    top.add_patch(Circle((0, 0), MERGE_ZONE_RADIUS_M, color=ZONE_COLOUR, alpha=0.35, lw=0, zorder=0))
    top.text(-main_len, 8, "main road", fontsize=8, color="0.35")
    top.text(
        -merge_len * np.cos(angle), -merge_len * np.sin(angle) - 18, "merge road", fontsize=8, color="0.35"
    )
    top.set_xlim(-max(main_len, merge_len * np.cos(angle)) - 10, out_len + 10)
    top.set_ylim(-merge_len * np.sin(angle) - 30, 40)
    top.set_aspect("equal")
    top.set_xlabel("metres from the merge point (sketch from above)")
    top.set_yticks([])


class TopViewFrames:
    """``rgb_array`` frames of one merge: the replay's view from above, the cars moved each frame."""

    def __init__(self, site: MergeSite) -> None:
        from matplotlib.figure import Figure

        self.figure = Figure(figsize=FRAME_SIZE_IN, dpi=FRAME_DPI)
        top: Any = self.figure.add_axes((0.03, 0.16, 0.94, 0.8))  # Any: as the replay's axes
        draw_roads(top, site)
        self.cars: Any = top.scatter([], [], s=46, marker="s", edgecolors="none", zorder=3)
        ring = {"s": 150, "marker": "o", "facecolors": "none", "zorder": 4}
        self.ego_ring: Any = top.scatter([], [], edgecolors="black", lw=1.2, **ring)
        self.clock = top.text(0.98, 0.96, "", transform=top.transAxes, ha="right", va="top", fontsize=9)

    def frame(
        self,
        road: np.ndarray,
        dist: np.ndarray,
        colours: list[tuple[int, int, int]],
        ego: npt.NDArray[np.bool_],
        time_s: float,
    ) -> npt.NDArray[np.uint8]:
        """(320, 640, 3) uint8: cars at ``dist`` metres before the merge point on ``road`` ("main",
        "merge" or "out"), coloured, the ``ego`` ones ringed."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        x, y = view_xy(road, dist)
        xy = np.column_stack([x, y]) if len(x) else np.empty((0, 2))
        self.cars.set_offsets(xy)
        self.cars.set_facecolors([(r / 255, g / 255, b / 255) for r, g, b in colours] or "none")
        self.ego_ring.set_offsets(xy[ego] if ego.any() else np.empty((0, 2)))
        self.clock.set_text(f"t = {time_s:.1f} s")
        canvas = FigureCanvasAgg(self.figure)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


def slot_frame(view: TopViewFrames, engine: MergeEngine, k: int, ego: str) -> npt.NDArray[np.uint8]:
    """An ``rgb_array`` frame of the engine's slot k now, ``ego`` ringed."""
    snap = engine.snapshot
    rows = engine.rows_of(k)
    ids = snap.ids[rows]
    road = np.array([ROAD_NAMES[c] for c in snap.road[rows].tolist()], dtype=object)
    specs = [engine.spec(k, v) for v in ids]
    colours = [vehicle_colour(s.road, s.b_type, s.controlled) for s in specs]
    is_ego = np.array([v == ego for v in ids], dtype=np.bool_)
    return view.frame(road, snap.dist_to_merge_m[rows], colours, is_ego, engine.time_s)
