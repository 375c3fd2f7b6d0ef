"""Pictures for benchmarks/uncertainty_calibration.py: the reliability diagram and a figure like the paper's Fig. 4."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from monai_probreg.metrics.calibration import reliability_bins

__all__ = ["reliability_diagram", "figure4"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


def reliability_diagram(curves: Mapping[str, tuple[np.ndarray, np.ndarray]], path: Path) -> None:
    """RMS observed error against RMS predicted std in 15 equal-count bins, one curve per (std, error) pair."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 4.8), layout="constrained")
    low, high = np.inf, 0.0
    for i, (name, (std, error)) in enumerate(curves.items()):
        bins = reliability_bins(std, error, num_bins=15)
        ax.plot(bins.rms_std, bins.rms_error, "o-", color=f"C{i}", label=name)
        low, high = (
            min(low, bins.rms_std.min(), bins.rms_error.min()),
            max(high, bins.rms_std.max(), bins.rms_error.max()),
        )
    ax.plot([low, high], [low, high], "k--", lw=1, label="perfect calibration (y = x)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("predicted std per bin (RMS, voxels)")
    ax.set_ylabel("observed error per bin (RMS, voxels)")
    ax.set_title("Displacement uncertainty, held-out subjects")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    _save(fig, path)
    plt.close(fig)


def figure4(
    pair: dict, labels: dict, velocity_entropy: torch.Tensor, displacement_std: torch.Tensor, path: Path, subject: str
) -> None:
    """One axial slice: atlas, subject, velocity entropy and displacement std over the atlas, label entropy over the
    subject with the wrongly labelled voxels outlined. All maps (*S) on the LPBA40 grid shared by atlas and subject."""
    plt = _pyplot()
    z = pair["fixed"].shape[-1] // 2
    take = lambda t: np.asarray(t[..., z].detach().cpu().float()).T  # noqa: E731  array axis 0 horizontal
    atlas, moving = take(pair["fixed"][0, 0]), take(pair["moving"][0, 0])
    wrong = take(
        ((labels["predicted"] != labels["truth"]) & ((labels["predicted"] > 0) | (labels["truth"] > 0))).float()
    )
    panels = [
        ("atlas (fixed)", atlas, None),
        (f"{subject} (moving)", moving, None),
        ("velocity entropy (nats)", atlas, take(velocity_entropy)),
        ("displacement std (voxels)", atlas, take(displacement_std)),
        ("atlas-label entropy over subject", moving, take(labels["entropy"])),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.9), layout="constrained")
    for ax, (title, background, overlay) in zip(axes, panels):
        ax.imshow(background, cmap="gray", origin="lower")
        if overlay is not None:
            shown = np.ma.masked_where(background <= 0, overlay)
            im = ax.imshow(shown, cmap="inferno", origin="lower", alpha=0.75)
            fig.colorbar(im, ax=ax, shrink=0.7)
        if title.startswith("atlas-label"):
            ax.contour(wrong, levels=[0.5], colors="cyan", linewidths=0.4)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(
        f"Calibrated uncertainty, {subject} -> atlas, axial slice {z} (cyan: wrongly propagated labels)", fontsize=10
    )
    _save(fig, path)
    plt.close(fig)
