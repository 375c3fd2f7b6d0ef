"""monai_probreg.registration.qc: the QC figure renders (with and without labels), atomically, and closes its figure."""

from __future__ import annotations

import dataclasses

import matplotlib.pyplot as plt
import numpy as np
import pytest
from conftest import asymmetric_phantom

from monai_probreg.registration.qc import QCData, qc_figure, qc_planes, save_qc


def _data(with_labels: bool, constant_uncertainty: bool = False) -> QCData:
    image, labels = asymmetric_phantom((24, 28, 20))
    rng = np.random.default_rng(0)
    displacement = 0.5 * rng.standard_normal((3, *image.shape)).astype(np.float32)
    uncertainty = np.full(image.shape, 1.7) if constant_uncertainty else rng.random(image.shape)
    jacobian = 1.0 + 0.3 * rng.standard_normal(image.shape)
    jacobian[10, 10, 10] = -0.2  # one folding voxel
    return QCData(
        fixed=image,
        moving=np.roll(image, 2, axis=0),
        warped=image,
        displacement=displacement,
        jacobian=jacobian,
        uncertainty=uncertainty,
        uncertainty_name="velocity entropy",
        spacing=(1.0, 1.2, 0.9),
        fixed_label=labels if with_labels else None,
        moving_label=np.roll(labels, 2, axis=0) if with_labels else None,
        warped_label=labels if with_labels else None,
        title="S11   mean Dice 0.812",
    )


@pytest.mark.parametrize("with_labels", [True, False])
def test_figure_layout(with_labels):
    fig = qc_figure(_data(with_labels))
    try:
        axes = fig.get_axes()
        panels, bars = axes[:18], axes[18:]  # 3 x 6 panels (row-major), then the two colour bars
        assert len(bars) == 2
        assert [ax.get_title() for ax in panels[:6]] == [
            "fixed",
            "moving (affine only)",
            "warped moving",
            "deformation (deformable part)",
            "Jacobian determinant",
            "velocity entropy",
        ]
        assert [panels[6 * row].get_ylabel().split()[0] for row in range(3)] == ["axial", "coronal", "sagittal"]
        assert fig._suptitle is not None and "Dice" in fig._suptitle.get_text()
    finally:
        plt.close(fig)


def test_save_writes_a_png_and_closes_the_figure(tmp_path):
    before = plt.get_fignums()
    path = save_qc(tmp_path / "qc.png", _data(True, constant_uncertainty=True))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plt.get_fignums() == before
    assert [p.name for p in tmp_path.iterdir()] == ["qc.png"]  # no temporary file left


def test_a_warning_is_drawn_in_red_under_the_title():
    fig = qc_figure(dataclasses.replace(_data(True), warning="this registration probably failed"))
    try:
        text = fig._suptitle.get_text()
        assert text.startswith("S11") and "WARNING: this registration probably failed" in text
        assert fig._suptitle.get_color() == "red"
    finally:
        plt.close(fig)
    fig = qc_figure(_data(True))
    try:
        assert "WARNING" not in fig._suptitle.get_text() and fig._suptitle.get_color() != "red"
    finally:
        plt.close(fig)


def test_the_slices_draw_the_same_figure_as_the_volumes(tmp_path):
    """A figure drawn from the slices (cut before the volumes go, labels added later) is the volumes' to the byte."""
    data = _data(True)
    whole = save_qc(tmp_path / "whole.png", data).read_bytes()
    no_labels = dataclasses.replace(data, fixed_label=None, moving_label=None, warped_label=None)
    planes = qc_planes(no_labels).with_labels(
        fixed_label=data.fixed_label, moving_label=data.moving_label, warped_label=data.warped_label
    )
    assert save_qc(tmp_path / "planes.png", planes).read_bytes() == whole
    assert save_qc(tmp_path / "direct.png", qc_planes(data)).read_bytes() == whole
    assert all(p.ndim == 2 for row in planes.rows for p in row.values())  # slices only, no volume kept
    with pytest.raises(ValueError, match="expected label names"):
        planes.with_labels(labels=data.fixed_label)
