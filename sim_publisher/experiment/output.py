"""Output files of the Table-1 experiment: in ``out_dir``, ``results.csv`` and one figure per
setup (``setupN.png``, like the paper's Fig. 7 and 8); beside it, the results page
``<out_dir>.md`` (``docs/results/experiment.md`` by default)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sim_publisher import results_page
from sim_publisher.experiment.results import BLOCK_TITLES, METHOD_NAMES, ExperimentResult
from sim_publisher.plot import plot_map, plot_path


def write_outputs(result: ExperimentResult, out_dir: Path, setup_objs: dict | None) -> list[Path]:
    """Write ``results.csv`` and (if ``setup_objs`` is given) one PNG per setup into
    ``out_dir``, and the page ``<out_dir>.md`` (overwritten) beside it; returns the written
    paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "results.csv"]
    result.write_csv(paths[0])
    figures = []
    if setup_objs is not None:
        for s, obj in setup_objs.items():
            paths.append(plot_setup(result, s, obj, out_dir / f"setup{s}.png"))
            figures.append(f"{out_dir.name}/setup{s}.png")
    page = out_dir.with_suffix(".md")
    paths.append(results_page.write_page(page, result.markdown(figures)))
    return paths


def plot_setup(result: ExperimentResult, setup_id: int, setup_obj: Any, path: Path) -> Path:
    """One panel per method: the map, the true path and that method's estimates (like the
    paper's Fig. 7 and 8). Needs matplotlib (imported here, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = result.ordered_methods(setup_id)
    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 6.5), squeeze=False)
    truth = np.asarray(setup_obj.truth)
    for ax, m in zip(axes[0], methods, strict=True):
        r = result.runs[(setup_id, m)]
        plot_map(ax, setup_obj.map_data, color="0.3", linewidth=0.7)
        plot_path(ax, truth, color="k", linewidth=1.0, label="true path")
        ax.plot(
            r.estimates[:, 0], r.estimates[:, 1], ".", color="tab:red", markersize=1.5,
            label="estimates",
        )  # fmt: skip
        ax.set_title(
            f"{METHOD_NAMES.get(m, m)}: {r.mean_position_mm:.0f} mm, "
            f"{r.proximity_pct:.0f}% proximity",
            fontsize=9,
        )
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper right", fontsize=7, markerscale=4)
    fig.suptitle(f"setup {setup_id}: {BLOCK_TITLES.get(setup_id, '')}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
