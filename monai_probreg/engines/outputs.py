"""The bundle's registration outputs: one folder per subject of NIfTI files on the fixed grid.

The functional core of ``bundle/configs/inference.yaml`` and ``evaluate.yaml``; the engine handlers in
:mod:`monai_probreg.engines.handlers` call it once per subject. The package conventions apply
(``monai_probreg/__init__.py``), and:

- Every output lives on the **fixed (atlas) grid after preprocessing** (reoriented to RAS, padded to the
  divisor) and is written with that grid's affine, ``fixed.affine`` of the MetaTensor after the transforms:
  the moving image is warped into the fixed grid, so the outputs overlay the atlas in world coordinates.
- Layout: one folder per subject, ``output_dir/<id>/<name>.nii.gz`` with the names in :data:`OUTPUT_NAMES`.
- ``displacement.nii.gz``: float32, shape (X, Y, Z, 1, 3), NIfTI intent "vector" (1007). Component k (5th axis)
  is the displacement along array axis k of this file's grid, **in voxels**; pull back:
  ``warped[i] = moving[i + u(i)]``. In millimetres (world axes): ``affine[:3, :3] @ u``. (ITK/ANTs expect mm
  in LPS; convert before using the field there.)
- ``warped.nii.gz`` holds the moving image's intensities as the network saw them (percentile-scaled to [0, 1]).
- Files are written atomically: a temporary name in the same folder, then ``os.replace``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from torch import Tensor

from monai_probreg.blocks.warp import warp_labels
from monai_probreg.metrics.jacobian import jacobian_determinant
from monai_probreg.networks.probreg_net import RegistrationOutput
from monai_probreg.uncertainty.entropy import velocity_entropy
from monai_probreg.uncertainty.posterior_maps import PosteriorMaps
from monai_probreg.utils.files import atomic_write
from monai_probreg.utils.tensors import plain_tensor

__all__ = ["OUTPUT_NAMES", "SAMPLED_NAMES", "DISPLACEMENT_DESCRIPTION", "OUTPUTS_README", "save_nifti", "write_outputs"]


OUTPUT_NAMES = ("warped", "displacement", "jacobian", "entropy", "warped_label", "displacement_std", "label_entropy")


SAMPLED_NAMES = ("displacement_std", "label_entropy")  # need K >= 2 posterior samples (PosteriorMaps)


DISPLACEMENT_DESCRIPTION = "displacement in voxels, comp k = array axis k; warped[i]=moving[i+u(i)]"


OUTPUTS_README = """\
Registration outputs of monai_probreg (VoxelMorph-diff), one folder per subject: <id>/<name>.nii.gz.
Every file lies on the atlas (fixed) grid as preprocessed (reoriented to RAS, padded to the divisor) and carries
that grid's affine, so it overlays the atlas in world coordinates.
  warped.nii.gz        moving image resampled into the atlas grid (intensities percentile-scaled to [0, 1])
  displacement.nii.gz  float32 (X, Y, Z, 1, 3), NIfTI intent vector; component k = displacement along array
                       axis k of this grid, in VOXELS; pull back: warped[i] = moving[i + u(i)];
                       in millimetres (world axes): affine[:3, :3] @ u (ITK/ANTs expect mm, LPS)
  jacobian.nii.gz      det(I + grad u) of x -> x + u(x); <= 0 marks folding
  entropy.nii.gz       entropy (nats) of the calibrated velocity posterior q(z) (Dalca et al. 2018, Eq. 8),
                       resized to this grid; relative: compare regions, not absolute values
  warped_label.nii.gz  moving labels warped nearest neighbour (written when labels exist)
  displacement_std.nii.gz  sqrt(sum of the 3 variances) of the displacement under the calibrated posterior, first
                       order (its velocity std resized onto this grid; no sampling), in voxels: how far,
                       roughly, each voxel's correspondence may be off; a component's
                       calibrated p-interval is +- t(p) times its own std (about this map / sqrt(3)), t the
                       Student-t quantile with the calibration sidecar's interval_dof (calibration and its limits:
                       the bundle docs, "Uncertainty")
  label_entropy.nii.gz entropy (nats) of the moving labels read by K posterior samples with partial volume (each
                       sample weighs the labels around its point as linear interpolation does): 0 = every sample
                       reads one label wholly; high values flag voxels whose warped label is likely wrong (written
                       when labels exist)
"""


def save_nifti(
    path: str | os.PathLike, data: np.ndarray, affine: np.ndarray, description: str = "", intent: str | None = None
) -> Path:
    """Write ``data`` (array axes = the affine's voxel axes) atomically; qform and sform both = ``affine``."""
    image = nib.Nifti1Image(data, np.asarray(affine, dtype=np.float64))
    image.set_qform(image.affine, code=1)
    image.set_sform(image.affine, code=1)
    image.header["descrip"] = description.encode()[:79]
    if intent is not None:
        image.header.set_intent(intent)
    return atomic_write(Path(path), lambda tmp: nib.save(image, tmp))


def write_outputs(
    output_dir: str | os.PathLike,
    subject_id: str,
    output: RegistrationOutput,
    affine: Tensor | np.ndarray,
    moving_label: Tensor | None = None,
    names: Sequence[str] = OUTPUT_NAMES,
    maps: PosteriorMaps | None = None,
) -> dict[str, Path]:
    """Write one subject's results into ``output_dir/<subject_id>/`` (see the module docstring).

    Shapes: ``output`` of one pair (B = 1) on the fixed grid S; ``affine`` (4, 4) of that grid;
    ``moving_label`` (1, 1, *S) integer, or None (no ``warped_label``). ``names``: which of :data:`OUTPUT_NAMES`
    to write. ``maps``: calibrated :class:`~monai_probreg.uncertainty.posterior_maps.PosteriorMaps` (then ``entropy`` is
    theirs, and :data:`SAMPLED_NAMES` are written when present); None: ``entropy`` of the raw posterior and no
    sampled maps. Returns {name: path written}.
    """
    unknown = set(names) - set(OUTPUT_NAMES)
    if unknown:
        raise ValueError(f"unknown output names {sorted(unknown)}; choose from {list(OUTPUT_NAMES)}")
    disp = output.displacement.detach().float()
    if disp.ndim != 5 or disp.shape[0] != 1:
        raise ValueError(f"expected one 3-d pair, displacement (1, 3, X, Y, Z); got {tuple(disp.shape)}")
    folder, aff, size = Path(output_dir) / subject_id, np.asarray(torch.as_tensor(affine).cpu()), disp.shape[2:]
    makers: dict[str, tuple[Callable[[], Tensor], str, str | None]] = {
        "warped": (lambda: output.warped[0, 0], "moving image warped to the fixed grid, intensities in [0, 1]", None),
        "displacement": (lambda: disp[0].movedim(0, -1).unsqueeze(-2), DISPLACEMENT_DESCRIPTION, "vector"),
        "jacobian": (lambda: jacobian_determinant(disp)[0], "Jacobian determinant of x -> x + u(x)", None),
        "entropy": (
            lambda: (
                velocity_entropy(output.velocity_log_var.float(), size)[0, 0] if maps is None else maps.velocity_entropy
            ),
            "velocity entropy" + (" (raw)" if maps is None else ""),
            None,
        ),
        "displacement_std": (
            lambda: maps.displacement_std,
            "first-order displacement std of the posterior, voxels",
            None,
        ),
        "label_entropy": (
            lambda: maps.label_entropy,
            "entropy of labels read by posterior samples (partial volume)",
            None,
        ),
        "warped_label": (
            lambda: warp_labels(plain_tensor(moving_label).to(disp.device), disp)[0, 0].to(torch.int16),
            "moving labels warped to the fixed grid, nearest neighbour",
            None,
        ),
    }
    written = {}
    for name in names:
        if name == "warped_label" and moving_label is None:
            continue
        if name in SAMPLED_NAMES and (maps is None or getattr(maps, name) is None):
            continue
        compute, description, intent = makers[name]
        array = plain_tensor(compute()).detach().cpu().numpy()
        array = array if array.dtype == np.int16 else array.astype(np.float32)
        written[name] = save_nifti(folder / f"{name}.nii.gz", array, aff, description, intent)
    return written
