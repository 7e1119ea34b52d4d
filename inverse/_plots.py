"""A picture of a light fit: the targets coloured by their residual, and where to paint more.

Matplotlib (the `plot` extra) with its Agg canvas (no display, no pyplot state); the file is
written through `jaxshadow.files.atomic_write_path`.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

import jaxshadow as js

from ._painting import LUMINANCE
from ._targets import PaintedTargets


def _plane_axes(points: np.ndarray) -> np.ndarray:
    """The two coordinate axes along which the points spread most (a floor: x and y)."""
    extent = points.max(axis=0) - points.min(axis=0)
    return np.sort(np.argsort(extent)[::-1][:2])


def plot_residuals(fit: Any, targets: PaintedTargets, path: str | os.PathLike, *, dpi: int = 120) -> None:
    """Write a picture of `fit`'s targets coloured by their residual, with the suggested target
    locations of its undetermined parameters marked.

    The targets are drawn in the plane of the two coordinates they spread most along (seen
    from above for floor targets), each coloured by the luminance of its residual
    ($0.2126 r_R + 0.7152 r_G + 0.0722 r_B$, model minus painted, W m^-2 sr^-1; a ranged
    target's distance outside its range) on a diverging scale symmetric about 0; targets of
    weight 0 are hollow. Each undetermined parameter's suggested locations
    (`fit.report.suggestions`, best first, up to 5) are crosses, one colour per parameter,
    named in the legend.

    **Arguments:**

    - `fit`: a `LightsFit` (`inverse.fit_lights`) or any result with `.residual (N, 3)` and a
      `.report` (its `suggestions`, if any, are drawn).
    - `targets`: the `PaintedTargets` the fit was made from (`N` targets).
    - `path`: the image file; the format follows its extension (`.png`, `.pdf`, `.svg`).
    - `dpi`: resolution of raster formats.

    **Returns:** None (the file is written atomically: a failure leaves an existing file).

    Example:
        ```python
        # fit = inverse.fit_lights(scene, targets, material)
        # inverse.plot_residuals(fit, targets, "residuals.png")
        ```
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - the plot extra is missing
        raise ImportError("plot_residuals needs matplotlib (pip install 'jaxshadow[plot]').") from e
    pts = np.asarray(targets.points, np.float64)
    res = np.asarray(fit.residual, np.float64)
    if res.shape != pts.shape:
        raise ValueError(f"plot_residuals: the fit has {res.shape[0]} residuals but targets has {pts.shape[0]} "
                         "points: pass the targets the fit was made from.")
    ext = os.path.splitext(os.fspath(path))[1].lower().lstrip(".") or "png"
    ax_idx = _plane_axes(pts)
    xy = pts[:, ax_idx]
    lum = res @ LUMINANCE
    lim = max(float(np.max(np.abs(lum))), 1e-300)
    weighted = np.any(np.asarray(targets.weights) > 0, axis=1)

    fig = Figure(figsize=(6.4, 5.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    sc = ax.scatter(xy[weighted, 0], xy[weighted, 1], c=lum[weighted], cmap="coolwarm", vmin=-lim, vmax=lim,
                    s=36, edgecolors="k", linewidths=0.3, label="targets")
    if not np.all(weighted):
        ax.scatter(xy[~weighted, 0], xy[~weighted, 1], facecolors="none", edgecolors="0.4", s=36,
                   label="weight 0")
    fig.colorbar(sc, ax=ax, label="residual luminance (model - painted)")
    suggestions = getattr(getattr(fit, "report", None), "suggestions", None) or {}
    markers = {}
    for name, where in suggestions.items():
        w = np.asarray(where, np.float64)[:5]
        if not len(w):
            continue
        key = w.tobytes()  # parameters sharing a null direction share their locations: one mark
        if key in markers:
            markers[key][0].append(name)
            continue
        markers[key] = ([name], w)
    colours = ["tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]
    for n, (names, w) in enumerate(markers.values()):
        ax.scatter(w[:, ax_idx[0]], w[:, ax_idx[1]], marker="x", s=70, linewidths=2,
                   color=colours[n % len(colours)], label="paint here: " + ", ".join(names))
    labels = "xyz"
    ax.set_xlabel(f"{labels[ax_idx[0]]} (m)")
    ax.set_ylabel(f"{labels[ax_idx[1]]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    loss = getattr(getattr(fit, "report", None), "loss", None)
    ax.set_title("targets by residual" + ("" if loss is None else f" (loss {loss:.3g})"))
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    js.files.atomic_write_path(path, lambda tmp: fig.savefig(tmp, format=ext, dpi=dpi))
