"""The ``compose`` stage of one registration: affine + deformable -> one field fixed -> moving and its inverse
(:mod:`monai_probreg.spatial.physical`), the original moving scan and labels resampled once through it, Dice
(:func:`compose_outputs`); and the resampling through the affine alone (:func:`affine_resample`, the ``resample``
stage's). All of it slab by slab of the output grid.

Every whole-grid point, index and field array of these steps is float64 (*S, 3): 400 MB each on a 256^3 grid, and
the steps used to hold several at once (the command's peak memory, ``benchmarks/end_to_end.py --memory``). Here
each is made for a slab of rows of the output grid's first axis at a time
(:func:`~monai_probreg.spatial.physical.row_slabs`), and every value is computed from its own voxel's index
exactly as on the whole grid (:func:`~monai_probreg.spatial.physical.index_map`'s ``first_row``), so the outputs
are the same to the bit (``tests/registration/test_compose.py``). What is kept is only what is written, at the
precision it is written in: the fields float32, the scans float32, the labels in their own type.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from monai_probreg.metrics.dice import label_dice, mean_dice
from monai_probreg.metrics.jacobian import JacobianStats, jacobian_stats
from monai_probreg.registration.inputs import FixedSpace
from monai_probreg.registration.network import ModelMaps
from monai_probreg.spatial.model_grid import ModelGrid
from monai_probreg.spatial.physical import compose_forward, compose_inverse, mapped_index, row_slabs, voxel_to_mm
from monai_probreg.spatial.point_sampling import LinearSampler, sample_nearest
from monai_probreg.spatial.volume_io import Volume
from monai_probreg.utils.memory import trim_freed_memory

__all__ = ["Composed", "Forward", "Inverse", "affine_resample", "compose_outputs", "forward_outputs", "inverse_outputs"]


def affine_resample(moving: Volume, fixed: Volume, affine: np.ndarray, fill: float) -> np.ndarray:
    """``moving`` on ``fixed``'s grid through ``affine`` (fixed LPS -> moving LPS): linear, ``fill`` outside the
    scan; float32 (:func:`~monai_probreg.spatial.point_sampling.sample_linear`'s values, rounded as the intensity
    scaling that reads them rounds them)."""
    out = np.empty(fixed.shape, np.float32)
    scan = LinearSampler(moving, fill=fill)
    for rows in row_slabs(fixed.shape):
        slab = (rows.stop - rows.start, *fixed.shape[1:])
        index = mapped_index(slab, fixed.index_to_lps, moving.index_to_lps, affine, first_row=rows.start)
        out[rows] = scan(None, index=index)
    return out


class Forward(NamedTuple):
    """The fixed grid's outputs: ``warp`` (*S, 3) float32, the composed ``D(p) = A(p + d(p)) - p`` in LPS mm;
    ``warped`` (*S) float32, the moving scan sampled at ``p + D(p)``; ``labels``: ``warped_label`` (there too) and
    ``affine_label`` (through the affine alone), nearest neighbour, with moving labels (else empty)."""

    warp: np.ndarray
    warped: np.ndarray
    labels: dict[str, np.ndarray]


def forward_outputs(
    grid: ModelGrid,
    fixed: Volume,
    moving: Volume,
    moving_label: Volume | None,
    affine: np.ndarray,
    displacement: np.ndarray,
) -> Forward:
    """``displacement``: the network's ``u`` (3, *grid.shape), voxels of the model ``grid`` of ``fixed``.

    Per slab of the fixed grid: ``d`` in mm (:func:`~monai_probreg.spatial.physical.voxel_to_mm` of the model grid's
    block that holds the slab, :meth:`~monai_probreg.spatial.model_grid.ModelGrid.block_of_rows`), the composed field
    (float32: the precision of its file), then the scan and labels sampled at ``p + D(p)`` with that float32 ``D``,
    exactly where ITK's resampling through ``warp.nii.gz`` samples them."""
    shape = fixed.shape
    warp = np.empty((*shape, 3), np.float32)
    warped = np.empty(shape, np.float32)  # sample_linear's float64, rounded as the file is written
    labels = {} if moving_label is None else {k: np.empty(shape, moving_label.array.dtype) for k in _FORWARD_LABELS}
    scan = LinearSampler(moving)
    for rows in row_slabs(shape):
        slab = (rows.stop - rows.start, *shape[1:])
        block = (slice(None), *grid.block_of_rows(rows))
        deformable = grid.block_to_fixed(voxel_to_mm(displacement[block], grid.index_to_lps))
        warp[rows] = compose_forward(deformable, fixed.index_to_lps, affine, first_row=rows.start)
        del deformable
        index = mapped_index(slab, fixed.index_to_lps, moving.index_to_lps, field=warp[rows], first_row=rows.start)
        warped[rows] = scan(None, index=index)
        if moving_label is not None:
            labels["warped_label"][rows] = sample_nearest(moving_label, None, index=index)
            index = mapped_index(slab, fixed.index_to_lps, moving.index_to_lps, affine, first_row=rows.start)
            labels["affine_label"][rows] = sample_nearest(moving_label, None, index=index)  # Dice and QC only
    return Forward(warp, warped, labels)


_FORWARD_LABELS = ("warped_label", "affine_label")


class Inverse(NamedTuple):
    """The moving grid's outputs: ``warp`` (*S_moving, 3) float32, ``D_inv(q) = phi^-1(q) - q`` in LPS mm;
    ``fixed_label`` (*S_moving): the fixed labels at ``q + D_inv(q)``, nearest neighbour (None without them)."""

    warp: np.ndarray
    fixed_label: np.ndarray | None


def inverse_outputs(
    grid: ModelGrid, inverse: np.ndarray, affine: np.ndarray, moving: Volume, fixed_label: Volume | None
) -> Inverse:
    """``inverse``: the network's ``exp(-v)`` displacement (3, *grid.shape) in voxels of the model ``grid``, float32;
    consumed: overwritten with its millimetres.

    Its millimetres are made per slab of the model grid and written back over the slab they came from (each slab is
    computed whole before it is stored), which leaves the float32, channels-first array that
    :func:`~monai_probreg.spatial.physical.compose_inverse` samples (it rounds ``d_inv`` to float32 itself, and a
    channels-first float32 array is taken without a copy): no second field of the model grid, no (*S, 3) float64
    field of the whole grid."""
    if inverse.dtype != np.float32:
        raise ValueError(f"expected the float32 displacement the network's maps hold; got {inverse.dtype}")
    for rows in row_slabs(grid.shape):
        inverse[:, rows] = voxel_to_mm(inverse[:, rows], grid.index_to_lps).transpose(3, 0, 1, 2)
    warp = compose_inverse(
        Volume(inverse.transpose(1, 2, 3, 0), grid.index_to_lps), affine, moving.shape, moving.index_to_lps
    )
    label = None
    if fixed_label is not None:  # q + D_inv(q) for every voxel q of the moving grid, in the fixed label grid
        label = np.empty(moving.shape, fixed_label.array.dtype)
        for rows in row_slabs(moving.shape):
            slab = (rows.stop - rows.start, *moving.shape[1:])
            index = mapped_index(
                slab, moving.index_to_lps, fixed_label.index_to_lps, field=warp[rows], first_row=rows.start
            )
            label[rows] = sample_nearest(fixed_label, None, index=index)
    return Inverse(warp, label)


@dataclass
class Composed:
    """Everything on the fixed grid (and the inverse on the moving grid) that is written, and the Jacobian's
    statistics; the fields are None once handed to their writers (:func:`~.scan.register_scan`: each goes once its
    file is written)."""

    warp: np.ndarray | None
    inverse_warp: np.ndarray | None  # None: not asked for (RegistrationOptions.inverse), or handed to its writer
    maps: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    dice: dict | None
    jacobian_stats: JacobianStats


def compose_outputs(
    fixed: FixedSpace,
    moving: Volume,
    moving_label: Volume | None,
    affine: np.ndarray,
    model_maps: ModelMaps,
    inverse: bool,
) -> Composed:
    """Affine + deformable -> one field each way; the original scan and labels resampled once; Dice
    (:func:`forward_outputs`, :func:`inverse_outputs`, slab by slab); the Jacobian's statistics.

    ``model_maps``' volumes are consumed: each is set to None once read (the inverse turned into millimetres in place),
    so that none is held beside what is made from it. The order keeps the stage's working set small: the maps and the
    Jacobian's statistics first (their temporaries beside nothing composed yet), then the inverse (the largest
    working set) before the forward outputs exist, then Dice; the freed memory is given back between the parts
    (:func:`~monai_probreg.utils.memory.trim_freed_memory`)."""
    grid = fixed.grid
    jacobian, entropy = grid.to_fixed(model_maps.jacobian), grid.to_fixed(model_maps.entropy)
    std = None if model_maps.std is None else grid.to_fixed(model_maps.std)
    model_maps.jacobian = model_maps.entropy = None
    stats = jacobian_stats(torch.from_numpy(jacobian))
    trim_freed_memory()  # each part's temporaries go back before the next, which allocates otherwise (memory.py)
    backward = None
    if inverse:
        backward = inverse_outputs(grid, model_maps.inverse, affine, moving, fixed.label)
        model_maps.inverse = None
        trim_freed_memory()
    forward = forward_outputs(grid, fixed.image, moving, moving_label, affine, model_maps.displacement)
    model_maps.displacement = None
    trim_freed_memory()
    maps = {"warped": forward.warped, "jacobian": jacobian, "entropy": entropy}
    if std is not None:
        maps["displacement_std"] = std
    labels = dict(forward.labels)
    inverse_warp = None
    if backward is not None:
        inverse_warp = backward.warp
        if backward.fixed_label is not None:
            labels["fixed_label_in_moving"] = backward.fixed_label
    dice = None
    if moving_label is not None and fixed.label is not None:
        # the structures both label maps have (a moving map of another protocol, e.g. LPBA40's 48 cortical labels
        # against the atlas' 56, is not charged for the labels it never had)
        ids = sorted(set(fixed.label_ids) & {int(v) for v in np.unique(moving_label.array) if v != 0})
        if ids:  # else no Dice (summary "dice": null): the two maps share no structure
            dice = _dice(labels["warped_label"], fixed.label, ids)
            affine_only = _dice(labels["affine_label"], fixed.label, ids)
            dice.update(
                mean_affine_only=affine_only["mean"],
                per_label_affine_only=affine_only["per_label"],
                labels="the non-zero labels of both label maps",
                num_fixed_only_labels=len(fixed.label_ids) - len(ids),
            )
    return Composed(forward.warp, inverse_warp, maps, labels, dice, stats)


def _dice(warped: np.ndarray, fixed: Volume, ids: list[int]) -> dict:
    per_label = label_dice(torch.from_numpy(warped), torch.from_numpy(fixed.array), ids)  # read in chunks, no copy
    mean = mean_dice(per_label)
    return {
        "mean": None if math.isnan(mean) else mean,  # JSON has no NaN: null
        "per_label": {str(k): (None if math.isnan(v) else round(v, 5)) for k, v in per_label.items()},
    }
