"""Study figures (PNG). Uses matplotlib's object API (``Figure``), no pyplot global state.

Inverse studies: error against wall time and against cumulative CG iterations (log-log, one
curve per configuration), K over the optimiser steps, recovered fields next to the truth.
Forward studies: error against K and time. h-studies: error against h and against run time.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.tri import Triangulation

from .._atomic import atomic_path
from ..inverse.history import History

if TYPE_CHECKING:
    import meshio

__all__ = ["forward_figures", "h_figures", "inverse_figures"]

_METRIC_LABEL = {"parameter_error": "relative L2 error of the recovered field",
                 "misfit": "misfit"}


def _save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    return path


def _positive(values) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    return np.where(values > 0, values, np.nan)


def _loglog_axes(xlabel: str, ylabel: str, title: str | None = None):
    """A figure with one log-log axes, labelled and gridded."""
    fig = Figure(figsize=(6.4, 4.4))
    ax = fig.subplots()
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    return fig, ax


def _curves(histories: dict[str, History], x: str, metric: str, xlabel: str, title: str,
            path: Path, ylabel: str | None = None) -> Path:
    fig, ax = _loglog_axes(xlabel, ylabel or _METRIC_LABEL.get(metric, metric), title)
    for name, history in histories.items():
        ax.plot(_positive(history.column(x)), _positive(history.column(metric)),
                marker=".", markersize=3, label=name)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _iterations_over_steps(histories: dict[str, History], path: Path,
                           step_label: str = "optimiser step") -> Path:
    fig = Figure(figsize=(6.4, 4.0))
    ax = fig.subplots()
    for name, history in histories.items():
        if history[-1].rtol > 0 or not np.any(history.column("iterations")):
            continue  # a tolerance-mode run has no K to show, a solver-free one none at all
        ax.step(history.column("step"), history.column("iterations"), where="post",
                label=f"{name} (K)")
        adjoint = history.column("adjoint_iterations")
        if not np.array_equal(adjoint, history.column("iterations")):
            ax.step(history.column("step"), adjoint, where="post", linestyle="--",
                    label=f"{name} (K_adj)")
    ax.set_xlabel(step_label)
    ax.set_ylabel("CG iterations per solve")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # tolerance-mode runs draw nothing here
        ax.legend(fontsize=8)
    return _save(fig, path)


def _field_panel(ax, mesh: meshio.Mesh, name: str, limits) -> object:
    points = mesh.points
    block = mesh.cells[0]
    cells = block.data
    if block.type == "quad":
        cells = np.vstack([cells[:, [0, 1, 2]], cells[:, [0, 2, 3]]])
    if block.type in ("tetra", "hexahedron"):  # 3-D: the vertices near the mid-plane z = c
        z = points[:, 2]
        mid = 0.5 * (z.min() + z.max())
        slab = np.abs(z - mid) <= 0.5 * np.ptp(z) / max(round(len(z) ** (1 / 3)), 1)
        values = mesh.point_data.get(name)
        if values is None:  # cell data: centroids near the plane
            centroids = points[cells].mean(axis=1)
            slab = np.abs(centroids[:, 2] - mid) <= 0.1 * np.ptp(z)
            return ax.scatter(centroids[slab, 0], centroids[slab, 1], c=mesh.cell_data[name][0][
                slab], s=8, vmin=limits[0], vmax=limits[1])
        return ax.tricontourf(points[slab, 0], points[slab, 1], values[slab],
                              levels=np.linspace(limits[0], limits[1], 21))
    triangulation = Triangulation(points[:, 0], points[:, 1], cells)
    if name in mesh.point_data:
        return ax.tripcolor(triangulation, mesh.point_data[name], shading="gouraud",
                            vmin=limits[0], vmax=limits[1])
    values = mesh.cell_data[name][0]
    if block.type == "quad":
        values = np.concatenate([values, values])
    return ax.tripcolor(triangulation, facecolors=values, vmin=limits[0], vmax=limits[1])


def _values(mesh: meshio.Mesh, name: str) -> np.ndarray:
    if name in mesh.point_data:
        return np.asarray(mesh.point_data[name])
    return np.asarray(mesh.cell_data[name][0])


def fields_figure(vtu_files: dict[str, Path], path: Path) -> Path | None:
    """Truth (from the first file that has one) and each run's recovered field, one scale."""
    import meshio  # here: see prdp_fem.mesh.io

    meshes = {name: meshio.read(file) for name, file in vtu_files.items() if file.exists()}
    if not meshes:
        return None
    panels = [(name, mesh, "recovered") for name, mesh in meshes.items()]
    with_truth = [m for m in meshes.values() if "truth" in m.point_data or "truth" in m.cell_data]
    if with_truth:
        panels.insert(0, ("truth", with_truth[0], "truth"))
    panels = panels[:6]
    values = np.concatenate([_values(m, f) for _, m, f in panels])
    limits = (float(np.nanmin(values)), float(np.nanmax(values)))
    fig = Figure(figsize=(3.2 * len(panels), 3.2))
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    artist = None
    for ax, (title, mesh, name) in zip(axes, panels, strict=True):
        artist = _field_panel(ax, mesh, name, limits)
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(artist, ax=list(axes), shrink=0.8)
    return _save(fig, path)


def inverse_figures(name: str, histories: dict[str, History], metric: str, out: Path,
                    field_files: dict[str, Path], *, metric_label: str | None = None,
                    step_label: str = "optimiser step") -> list[Path]:
    """The inverse-study figures under ``out/figures``; ``field_files``: run -> VTU file.

    Learned studies reuse them (one record per epoch): ``metric_label`` and ``step_label``
    name their axes."""
    histories = {n: h for n, h in histories.items() if len(h)}
    if not histories:
        return []
    figures = out / "figures"
    title = f"{name}: {metric_label or metric.replace('_', ' ')}"
    made = [
        _curves(histories, "time", metric, "wall time without compilation [s]", title,
                figures / "error_vs_time.png", metric_label),
        _curves(histories, "total_iterations", metric,
                "cumulative CG iterations (primal + adjoint)", title,
                figures / "error_vs_iterations.png", metric_label),
        _iterations_over_steps(histories, figures / "iterations_over_steps.png", step_label),
    ]
    field = fields_figure({n: field_files[n] for n in histories if n in field_files},
                          figures / "fields.png")
    return made + ([field] if field is not None else [])


def forward_figures(by_run: dict[str, list[dict]], out: Path) -> list[Path]:
    figures = out / "figures"
    made = []
    for x, label, file in (("requested_iterations", "CG iterations K", "error_vs_K.png"),
                           ("wall_time_s", "solve time [s]", "error_vs_time.png")):
        fig, ax = _loglog_axes(label, "relative energy-norm error (vs pyamg)")
        for name, records in by_run.items():
            ax.plot(_positive([r[x] for r in records]),
                    _positive([r["relative_energy_error"] for r in records]), marker="o",
                    label=name)
        ax.legend(fontsize=8)
        made.append(_save(fig, figures / file))
    return made


def h_figures(rows: list[dict], out: Path) -> list[Path]:
    figures = out / "figures"
    elements = sorted({r["element"] for r in rows})
    made = []
    for x, label, file in (("h", "mesh size h (longest edge)", "error_vs_h.png"),
                           ("time", "setup + solve time [s] (solid: PCG, dashed: pyamg)",
                            "error_vs_time.png")):
        fig, ax = _loglog_axes(label, "L2 error against the exact solution")
        for element in elements:
            mine = [r for r in rows if r["element"] == element]
            xs = [r["cg_setup_time"] + r["cg_time"] if x == "time" else r[x] for r in mine]
            line, = ax.plot(xs, [r["l2_error"] for r in mine], marker="o", label=element)
            if x == "time":
                ax.plot([r["amg_time"] for r in mine], [r["l2_error"] for r in mine],
                        marker="s", linestyle="--", color=line.get_color(),
                        label=f"{element} pyamg")
        ax.legend(fontsize=8)
        made.append(_save(fig, figures / file))
    return made
