"""Matplotlib helpers for maps, worlds and trajectories (matplotlib is an optional extra and is
imported lazily inside the functions that need it).

All coordinates are map-frame metres. ``python -m sim_publisher.plot [outdir]`` regenerates
``docs/office_world.png`` and ``docs/office_schematic.png``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from service.adapters.maps.world import World
from service.core.types import MapData


def plot_map(ax: Any, map_data: MapData, **style: Any) -> None:
    """Draw every polyline of ``map_data`` on ``ax`` (default: thin black lines)."""
    kw = {"color": "k", "linewidth": 0.8}
    kw.update(style)
    first = True
    for p in map_data.polylines:
        ax.plot(p[:, 0], p[:, 1], **kw)
        if first:
            kw.pop("label", None)
            first = False
    ax.set_aspect("equal")


def plot_world(
    ax: Any, world: World, wall_color: str = "0.35", obstacle_color: str = "0.6"
) -> None:
    """Fill the world's obstacles (walls darker than furniture)."""
    for o in world.obstacles:
        g = o.geometry
        color = wall_color if o.kind == "wall" else obstacle_color
        ax.fill(*g.exterior.xy, color=color, linewidth=0)
        for r in g.interiors:
            ax.fill(*r.xy, color="white", linewidth=0)
    ax.set_aspect("equal")


def plot_path(ax: Any, poses: np.ndarray, **style: Any) -> None:
    """Draw the positions of ``(n, 3)`` or ``(n, 2)`` poses as a line."""
    p = np.asarray(poses, dtype=np.float64)
    kw = {"color": "tab:blue", "linewidth": 1.2}
    kw.update(style)
    ax.plot(p[:, 0], p[:, 1], **kw)


def plot_poses(
    ax: Any, poses: np.ndarray, every: int = 1, length: float = 0.25, **style: Any
) -> None:
    """Draw heading arrows of length ``length`` m for every ``every``-th pose."""
    p = np.asarray(poses, dtype=np.float64)[::every]
    kw = {"color": "tab:red", "width": 0.002, "angles": "xy", "scale_units": "xy", "scale": 1.0}
    kw.update(style)
    ax.quiver(p[:, 0], p[:, 1], length * np.cos(p[:, 2]), length * np.sin(p[:, 2]), **kw)


def figure_axes(width_in: float = 5.0, height_in: float = 8.0) -> tuple[Any, Any]:
    """A new figure and axes without a display (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(width_in, height_in))
    return fig, ax


def save_office_figures(outdir: str | Path) -> list[Path]:
    """Write ``office_world.png`` (world, true tour, odometry) and ``office_schematic.png``
    into ``outdir``; returns the paths."""
    import matplotlib.pyplot as plt

    from sim_publisher.office import office_schematic_map, office_world
    from sim_publisher.scenario import make_setup

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    setup = make_setup(1)
    fig, ax = figure_axes()
    plot_world(ax, office_world())
    plot_path(ax, setup.truth, color="k", linewidth=1.4, label="true path")
    plot_path(ax, setup.odom, color="tab:blue", linestyle="--", linewidth=1.0, label="odometry")
    ax.plot(*setup.truth[0, :2], "go", label="start")
    ax.plot(*setup.truth[-1, :2], "rs", label="end")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title("office world (setup 1 tour)", fontsize=9)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    p1 = out / "office_world.png"
    fig.savefig(p1, dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, ax = figure_axes()
    plot_map(ax, office_schematic_map(), color="k", linewidth=1.0)
    ax.set_title("schematic map", fontsize=9)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    p2 = out / "office_schematic.png"
    fig.savefig(p2, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return [p1, p2]


if __name__ == "__main__":
    for path in save_office_figures(sys.argv[1] if len(sys.argv) > 1 else "docs"):
        print("wrote", path)
