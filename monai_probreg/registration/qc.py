"""The quality-control figure ``qc.png``: is this registration right, at a glance?

Rows: three orthogonal slices (axial, coronal, sagittal) through the fixed image's centre of mass. Columns:

1. fixed image, with its label outlines;
2. moving image after the affine alignment only, with its (affinely resampled) label outlines;
3. moving image after affine + deformable registration, with its warped label outlines
   (panels 1-3: when a map has no labels of its own, the fixed labels are outlined instead, as a reference);
4. the deformable part as a warped grid: lines every ``grid_mm`` of the fixed grid drawn where the deformation
   sends them in the (affinely aligned) moving image, in-plane components;
5. the Jacobian determinant of the deformable part (blue < 1 < red: shrinking / growing; black = folding, <= 0);
6. the uncertainty map (the first-order displacement std, or the velocity entropy without it).

Inputs are arrays on the model grid (:class:`~monai_probreg.spatial.model_grid.ModelGrid`: RAS axes, so axis 0 runs left to
right, 1 posterior to anterior, 2 inferior to superior); slices are drawn in millimetres with the patient's right
on the right of the axial and coronal panels (neurological convention), anterior on the right of the sagittal.
Rendered with matplotlib's Agg backend (no display needed).

The figure is drawn from slices (:class:`QCPlanes`, cut from the volumes by :func:`qc_planes`): a registration cuts
them while it still holds the network's volumes and lets those go before its outputs are written; the labels it
resamples later are cut then (:meth:`QCPlanes.with_labels`).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import patheffects  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.colors import ListedColormap, TwoSlopeNorm  # noqa: E402
from matplotlib.ticker import FormatStrFormatter  # noqa: E402

from monai_probreg.utils.files import atomic_write  # noqa: E402

__all__ = ["QCData", "QCPlanes", "qc_figure", "qc_planes", "save_qc"]

# (fixed axis, horizontal axis, vertical axis, name, left/right letters)
_VIEWS = ((2, 0, 1, "axial", "LR"), (1, 0, 2, "coronal", "LR"), (0, 1, 2, "sagittal", "PA"))


@dataclass
class QCData:
    """Everything :func:`qc_figure` draws; arrays (X, Y, Z) on the model grid, ``displacement`` (3, X, Y, Z) voxels."""

    fixed: np.ndarray
    moving: np.ndarray
    warped: np.ndarray
    displacement: np.ndarray
    jacobian: np.ndarray
    uncertainty: np.ndarray
    uncertainty_name: str
    spacing: tuple[float, float, float]
    fixed_label: np.ndarray | None = None
    moving_label: np.ndarray | None = None
    warped_label: np.ndarray | None = None
    title: str = ""
    grid_mm: float = 5.0
    warning: str | None = None  # the quality estimate's warning, drawn in red under the title


def _centre(image: np.ndarray) -> tuple[int, ...]:
    weights = np.clip(image, 0, None)
    if weights.sum() <= 0:
        return tuple(n // 2 for n in image.shape)
    grids = np.meshgrid(*[np.arange(n) for n in image.shape], indexing="ij", sparse=True)
    return tuple(int(round(float((g * weights).sum() / weights.sum()))) for g in grids)


def _plane(volume: np.ndarray, axis: int, index: int) -> np.ndarray:
    return np.take(volume, index, axis=axis).T  # rows = vertical axis, columns = horizontal axis


_IMAGES = ("fixed", "moving", "warped")
_LABELS = ("fixed_label", "moving_label", "warped_label")


@dataclass
class QCPlanes:
    """What :func:`qc_figure` draws, cut from :class:`QCData`'s volumes by :func:`qc_planes`: ``rows``, one per view
    of the figure (axial, coronal, sagittal), each the slices through the fixed image's centre of mass (``centre``,
    model-grid voxels) by name: the images and labels (``QCData``'s names; a label None without it), ``jacobian``,
    ``uncertainty``, and ``uh`` / ``uv``, the displacement's components along the slice's horizontal and vertical
    axes; ``unc_range``: the uncertainty's colour range, over the whole volume's foreground."""

    rows: list[dict[str, np.ndarray | None]]
    centre: tuple[int, ...]
    shape: tuple[int, ...]
    spacing: tuple[float, float, float]
    unc_range: tuple[float, float]
    uncertainty_name: str
    title: str = ""
    grid_mm: float = 5.0
    warning: str | None = None

    def with_labels(self, **labels: np.ndarray | None) -> QCPlanes:
        """A copy with the label volumes given by name (``fixed_label``, ``moving_label``, ``warped_label``; (X, Y,
        Z) on the model grid, or None) cut through the same centre."""
        unknown = set(labels) - set(_LABELS)
        if unknown:
            raise ValueError(f"expected label names among {_LABELS}; got {sorted(unknown)}")
        rows = []
        for row, (axis, *_) in zip(self.rows, _VIEWS):
            cut = {k: None if v is None else _plane(v, axis, self.centre[axis]) for k, v in labels.items()}
            rows.append({**row, **cut})
        return dataclasses.replace(self, rows=rows)


def qc_planes(data: QCData) -> QCPlanes:
    """The slices of ``data`` that :func:`qc_figure` draws (:class:`QCPlanes`)."""
    centre = _centre(data.fixed)
    foreground = data.fixed > 0.05
    unc = data.uncertainty[foreground] if foreground.any() else data.uncertainty.ravel()
    unc_range = tuple(float(v) for v in np.percentile(unc, [2, 98]))  # one partial sort for both
    del unc, foreground
    if unc_range[1] - unc_range[0] < 1e-6 * max(1.0, abs(unc_range[0])):  # a constant map (e.g. untrained model)
        unc_range = (unc_range[0] - 0.5, unc_range[0] + 0.5)
    rows = []
    for axis, h, v, *_ in _VIEWS:
        index = centre[axis]
        row = {name: _plane(getattr(data, name), axis, index) for name in (*_IMAGES, "jacobian", "uncertainty")}
        row["uh"], row["uv"] = _plane(data.displacement[h], axis, index), _plane(data.displacement[v], axis, index)
        rows.append(row)
    planes = QCPlanes(
        rows,
        centre,
        tuple(data.fixed.shape),
        data.spacing,
        unc_range,
        data.uncertainty_name,
        data.title,
        data.grid_mm,
        data.warning,
    )
    return planes.with_labels(**{name: getattr(data, name) for name in _LABELS})


def _outline_rgba(labels: np.ndarray) -> np.ndarray:
    """RGBA image: label boundaries coloured by label id, transparent elsewhere."""
    edge = np.zeros(labels.shape, dtype=bool)
    edge[1:, :] |= labels[1:, :] != labels[:-1, :]
    edge[:-1, :] |= labels[1:, :] != labels[:-1, :]
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[:, :-1] |= labels[:, 1:] != labels[:, :-1]
    edge &= labels > 0
    colours = plt.get_cmap("tab20")(np.arange(20))
    rgba = np.zeros((*labels.shape, 4))
    rgba[edge] = colours[labels[edge] % 20]
    rgba[edge, 3] = 0.9
    return rgba


def qc_figure(data: QCData | QCPlanes) -> plt.Figure:
    """Build the figure (see the module docstring) of ``data`` or of its slices; the caller saves or closes it."""
    planes = data if isinstance(data, QCPlanes) else qc_planes(data)
    spacing = np.asarray(planes.spacing, dtype=np.float64)
    columns = [
        "fixed",
        "moving (affine only)",
        "warped moving",
        "deformation (deformable part)",
        "Jacobian determinant",
        planes.uncertainty_name,
    ]
    # a fixed layout (matplotlib's constrained layout costs a large share of the figure's time): panels, then a strip for the
    # colour bars under the last two columns; the title above
    fig, axes = plt.subplots(
        3,
        6,
        figsize=(18, 9.2),
        squeeze=False,
        gridspec_kw={"left": 0.025, "right": 0.995, "top": 0.9, "bottom": 0.1, "wspace": 0.03, "hspace": 0.1},
    )
    unc_range = planes.unc_range
    jac_norm = TwoSlopeNorm(vmin=0.0, vcenter=1.0, vmax=2.0)
    mappables = {}
    for row, ((axis, h, v, name, letters), cut) in enumerate(zip(_VIEWS, planes.rows)):
        index = planes.centre[axis]
        extent = (
            -0.5 * spacing[h],
            (planes.shape[h] - 0.5) * spacing[h],  # voxel i centred at i * spacing
            -0.5 * spacing[v],
            (planes.shape[v] - 0.5) * spacing[v],
        )
        show = dict(origin="lower", extent=extent, interpolation="nearest")
        for col, (image, label) in enumerate(zip(_IMAGES, _LABELS)):
            ax = axes[row, col]
            ax.imshow(cut[image], cmap="gray", vmin=0, vmax=1, **show)
            outline = cut[label] if cut[label] is not None else cut["fixed_label"]
            if outline is not None:
                ax.imshow(_outline_rgba(outline), **show)
        ax = axes[row, 3]
        ax.imshow(cut["fixed"], cmap="gray", vmin=0, vmax=1, alpha=0.35, **show)
        _draw_grid(ax, cut["uh"], cut["uv"], h, v, spacing, planes.grid_mm)
        ax = axes[row, 4]
        jac = cut["jacobian"]
        mappables["jac"] = ax.imshow(jac, cmap="RdBu_r", norm=jac_norm, **show)
        folding = np.ma.masked_where(jac > 0, np.ones_like(jac))
        ax.imshow(folding, cmap=ListedColormap(["black"]), **show)
        ax = axes[row, 5]
        mappables["unc"] = ax.imshow(cut["uncertainty"], cmap="magma", vmin=unc_range[0], vmax=unc_range[1], **show)
        for col in range(6):
            ax = axes[row, col]
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
            for x, letter, align in ((0.02, letters[0], "left"), (0.98, letters[1], "right")):
                ax.text(
                    x,
                    0.5,
                    letter,
                    transform=ax.transAxes,
                    color="yellow",
                    fontsize=10,
                    va="center",
                    ha=align,
                    path_effects=[patheffects.withStroke(linewidth=2, foreground="black")],
                )
            if row == 0:
                ax.set_title(columns[col], fontsize=11)
        axes[row, 0].set_ylabel(f"{name} {index}", fontsize=11)
    for key, col, label in (("jac", 4, "|J| (black: <= 0)"), ("unc", 5, planes.uncertainty_name)):
        cell = axes[-1, col].get_subplotspec().get_position(fig)  # the cell, not the (equal-aspect) image inside it
        strip = fig.add_axes((cell.x0 + 0.05 * cell.width, 0.055, 0.9 * cell.width, 0.012))
        bar = fig.colorbar(mappables[key], cax=strip, orientation="horizontal", label=label)
        bar.formatter = FormatStrFormatter("%.3g")
        bar.update_ticks()
    title = "\n".join(t for t in (planes.title, f"WARNING: {planes.warning}" if planes.warning else "") if t)
    if title:
        text = fig.suptitle(title, fontsize=12)
        if planes.warning:
            text.set_color("red")
    return fig


def _draw_grid(
    ax: plt.Axes, uh: np.ndarray, uv: np.ndarray, h: int, v: int, spacing: np.ndarray, grid_mm: float
) -> None:
    """Lines of constant h and constant v, every ``grid_mm``, drawn at (x + u(x)) in the plane, in mm; ``uh``,
    ``uv``: the displacement's components along h and v in the plane (voxels)."""
    rows, cols = uh.shape
    hh, vv = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    xs, ys = (hh + uh) * spacing[h], (vv + uv) * spacing[v]
    step_h = max(1, int(round(grid_mm / spacing[h])))
    step_v = max(1, int(round(grid_mm / spacing[v])))
    lines = [np.stack([xs[r, :], ys[r, :]], axis=-1) for r in range(0, rows, step_v)]
    lines += [np.stack([xs[:, c], ys[:, c]], axis=-1) for c in range(0, cols, step_h)]
    ax.add_collection(LineCollection(lines, colors="tab:blue", linewidths=0.6))  # one artist, not one per line


def save_qc(path: str | os.PathLike, data: QCData | QCPlanes, dpi: int = 90) -> Path:
    """Render :func:`qc_figure` to a PNG atomically and close the figure."""
    fig = qc_figure(data)
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))
    finally:
        plt.close(fig)
