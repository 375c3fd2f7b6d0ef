"""Physical-space transforms: voxel <-> millimetre displacements, composing affine + deformable, ITK objects.

Conventions, written once (pinned by ``tests/spatial/test_physical.py``):

1. Index order. Arrays are indexed ``(i, j, k)`` = ITK's index order = nibabel's array order.
   ``itk.GetArrayFromImage`` returns ``(k, j, i)``; :mod:`monai_probreg.spatial.volume_io` transposes on reading and writing.
2. Physical space is ITK's: LPS millimetres. A grid is a (4, 4) ``index_to_lps``:
   ``p = origin + direction @ diag(spacing) @ (i, j, k)``; nibabel's RAS affine is
   ``diag(-1, -1, 1, 1) @ index_to_lps``.
3. Our model's displacement ``u`` (3, *S) is in voxels of its grid, channel k along array axis k, and pulls back:
   ``warped[x] = moving[x + u(x)]``. Since ``p(x)`` is affine in x, ``p(x + u) = p(x) + R u`` with
   ``R = index_to_lps[:3, :3]``: the same map in millimetres is ``d(p) = R @ u(x)`` (:func:`voxel_to_mm`).
4. ITK's ``DisplacementFieldTransform`` (and ANTs' warp files) map a point of the **fixed** (output) space to the
   **moving** (input) space, ``T(p) = p + d(p)``, with ``d`` in LPS mm stored per fixed voxel as (d_L, d_P, d_S):
   exactly convention 3, so ``R @ u`` is an ITK/ANTs displacement field with no sign change.
5. Composition. ``--moving`` is first aligned by an affine ``A`` (fixed point -> original moving point, as ITK's
   registration returns it) and resampled onto the fixed grid; the model then gives ``d`` on the fixed grid. A fixed
   point goes ``p -> p + d(p) -> A(p + d(p))`` into the original moving scan, so the composed field on the fixed
   grid is ``D(p) = A(p + d(p)) - p`` (:func:`compose_forward`), exact at every fixed voxel (``A`` is affine, ``d``
   is evaluated where it is defined). Resampling the original moving scan once through ``D`` is what we write
   (one interpolation, as ``antsApplyTransforms`` does).
6. Inverse. With ``d_inv`` the model's inverse (``exp(-v)``) in mm, ``phi^-1(q) = a + d_inv(a)`` where
   ``a = A^-1(q)``; the inverse field lives on the **moving** grid, ``D_inv(q) = phi^-1(q) - q``
   (:func:`compose_inverse`), ``d_inv`` being interpolated linearly (border-extended outside its grid).
"""

from __future__ import annotations

import itk
import numpy as np
import torch

from monai_probreg.blocks.grid_coords import index_to_grid_matrix
from monai_probreg.blocks.warp import split_grid_sample
from monai_probreg.spatial.volume_io import Volume

__all__ = [
    "affine_from_itk",
    "affine_to_itk",
    "apply_affine",
    "compose_forward",
    "compose_inverse",
    "displacement_transform",
    "field_from_itk",
    "field_to_itk",
    "grid_points",
    "index_map",
    "mapped_index",
    "mm_to_voxel",
    "resample_with_itk",
    "row_slabs",
    "voxel_to_mm",
]

# voxels per slab of :func:`row_slabs` and :func:`compose_inverse`: a slab's (n, 3) float64 points stay near 25 MB,
# under glibc's largest mmap threshold (32 MB: without memory reuse they then come from the heap, freed slab after
# slab and reused), and a slab's several temporaries stay a small part of a 256^3 registration's peak
SLAB_VOXELS = 1 << 20


def row_slabs(shape: tuple[int, ...], voxels: int | None = None) -> list[slice]:
    """Whole rows of a grid's first axis, about ``voxels`` (default :data:`SLAB_VOXELS`) voxels at a time (at least
    one row per slab), in order: a whole-grid computation done per slab (:func:`index_map`'s ``first_row``) keeps its
    (*S, 3) float64 point and index arrays slab-sized (a 256^3 grid's are 400 MB each)."""
    voxels = SLAB_VOXELS if voxels is None else voxels
    rows = max(1, int(voxels) // max(1, int(np.prod(shape[1:]))))
    return [slice(start, min(start + rows, int(shape[0]))) for start in range(0, int(shape[0]), rows)]


def index_map(
    shape: tuple[int, ...], matrix: np.ndarray, offset: np.ndarray | None = None, first_row: int = 0
) -> np.ndarray:
    """``matrix[:3] @ (i, j, k, 1)`` (+ ``offset[i, j, k]``) for every voxel index of a grid of ``shape``: (I, J, K, 3)
    float64. Broadcast from three ``arange``s in torch (multi-threaded; no index array, no (N, 3) matmul).

    ``first_row``: ``shape`` is a slab of a larger grid, its rows ``first_row, first_row + 1, ...`` of the first axis
    (:func:`row_slabs`): each value is computed from its own index exactly as in the whole grid's map (folding the
    slab's start into the matrix's translation instead would round differently)."""
    m = torch.from_numpy(np.asarray(matrix, dtype=np.float64)[:3].copy())
    starts = (int(first_row), 0, 0)
    axes = [
        torch.arange(starts[axis], starts[axis] + n, dtype=torch.float64).view(
            [-1 if a == axis else 1 for a in range(3)]
        )
        for axis, n in enumerate(shape)
    ]
    out = torch.empty((*shape, 3), dtype=torch.float64)
    for c in range(3):
        torch.add(m[c, 0] * axes[0] + m[c, 3], m[c, 1] * axes[1] + m[c, 2] * axes[2], out=out[..., c])
    if offset is not None:
        out += torch.from_numpy(np.asarray(offset)).to(torch.float64)
    return out.numpy()


def grid_points(shape: tuple[int, ...], index_to_lps: np.ndarray) -> np.ndarray:
    """LPS points (I, J, K, 3) of every voxel centre of a grid, float64 (:func:`index_map` of ``index_to_lps``)."""
    return index_map(shape, index_to_lps)


def mapped_index(
    shape: tuple[int, ...],
    index_to_lps: np.ndarray,
    target_index_to_lps: np.ndarray,
    affine: np.ndarray | None = None,
    field: np.ndarray | None = None,
    first_row: int = 0,
) -> np.ndarray:
    """Where every voxel ``p`` of a grid lands in another: the continuous index, in the grid ``target_index_to_lps``,
    of ``A(p) + field(p)`` (I, J, K, 3) float64, ``A`` = ``affine`` (4, 4, default the identity), ``field`` (I, J, K, 3)
    LPS mm on the first grid (e.g. ``warp.nii.gz``'s ``D``, whose ``p + D(p)`` is the moving point of ``p``).

    Affine in the index apart from ``field``, so no point array is formed: ``T^-1 A G (i, j, k, 1) + T^-1 field``
    (``G``, ``T``: the two grids' index -> LPS matrices). ``field`` is used at the precision it is given: pass the
    float32 field that is written, and the result is the index ITK's resampling through that file computes.
    ``first_row``: ``shape`` (and ``field``) are the slab of the grid from that row of its first axis on
    (:func:`index_map`'s, :func:`row_slabs`): the same values as that slab of the whole grid's map."""
    target_inverse = np.linalg.inv(np.asarray(target_index_to_lps, dtype=np.float64))
    matrix = (
        target_inverse
        @ (np.eye(4) if affine is None else np.asarray(affine, np.float64))
        @ np.asarray(index_to_lps, np.float64)
    )
    offset = None
    if field is not None:
        flat = torch.from_numpy(np.asarray(field)).to(torch.float64).reshape(-1, 3)
        offset = (flat @ torch.from_numpy(target_inverse[:3, :3].T.copy())).view(*shape, 3)
    return index_map(shape, matrix, None if offset is None else offset.numpy(), first_row)


def voxel_to_mm(displacement: np.ndarray, index_to_lps: np.ndarray) -> np.ndarray:
    """Voxel displacement (3, *S), channel k along array axis k -> LPS millimetres (*S, 3): ``R @ u``."""
    if displacement.ndim != 4 or displacement.shape[0] != 3:
        raise ValueError(f"expected a (3, I, J, K) displacement in voxels; got {displacement.shape}")
    return np.einsum("ck,k...->...c", np.asarray(index_to_lps, dtype=np.float64)[:3, :3], displacement)


def mm_to_voxel(field: np.ndarray, index_to_lps: np.ndarray) -> np.ndarray:
    """Inverse of :func:`voxel_to_mm`: LPS mm (*S, 3) -> voxels (3, *S) of the grid ``index_to_lps``."""
    inverse = np.linalg.inv(np.asarray(index_to_lps, dtype=np.float64)[:3, :3])
    return np.einsum("kc,...c->k...", inverse, field)


def apply_affine(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``matrix`` (4, 4) applied to points (..., 3), float64, as one multi-threaded ``torch.addmm`` (numpy runs the
    (N, 3) x (3, 3) product on one core; ``experiments/command_levers.py`` times both)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    flat = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3))
    out = torch.addmm(torch.from_numpy(matrix[:3, 3].copy())[None], flat, torch.from_numpy(matrix[:3, :3].T.copy()))
    return out.numpy().reshape(np.shape(points))


def compose_forward(
    deformable_mm: np.ndarray, fixed_index_to_lps: np.ndarray, affine: np.ndarray, first_row: int = 0
) -> np.ndarray:
    """Composed field on the fixed grid, ``D(p) = A(p + d(p)) - p`` (*S, 3) mm, float64 (module docstring, item 5).

    ``deformable_mm``: ``d`` (*S, 3) on the fixed grid, or the slab of it from row ``first_row`` on (:func:`index_map`'s
    ``first_row``); ``affine``: ``A`` (4, 4), fixed LPS -> moving LPS.
    With ``p = G (i, j, k, 1)``: ``D = (A G - G)(i, j, k, 1) + A_lin d``, so no point array is formed."""
    affine = np.asarray(affine, dtype=np.float64)
    grid = np.asarray(fixed_index_to_lps, dtype=np.float64)
    flat = torch.from_numpy(np.asarray(deformable_mm)).to(torch.float64).reshape(-1, 3)
    moved = flat @ torch.from_numpy(affine[:3, :3].T.copy())
    shape = deformable_mm.shape[:3]
    return index_map(shape, affine @ grid - grid, moved.view(*shape, 3).numpy(), first_row)


def compose_inverse(
    inverse_mm: Volume,
    affine: np.ndarray,
    moving_shape: tuple[int, ...],
    moving_index_to_lps: np.ndarray,
    rows_per_chunk: int | None = None,
) -> np.ndarray:
    """Composed inverse on the moving grid, ``D_inv(q) = a + d_inv(a) - q`` with ``a = A^-1(q)`` (*S_moving, 3) mm,
    float32 (the precision of the field file it becomes).

    ``inverse_mm``: ``d_inv`` (*S, 3) in mm on its grid (the fixed or model grid), as a :class:`Volume`; linear,
    border-extended outside it (:func:`~monai_probreg.spatial.point_sampling.sample_linear`'s ``"border"``).

    Computed per slab of the moving grid's first axis without any point array: ``a`` and the continuous index of
    ``a`` in ``d_inv``'s grid are affine in the moving voxel index (``A^-1 @ moving_index_to_lps``), so both come from
    :func:`index_map` and ``d_inv`` is read with one ``grid_sample`` per slab (float32 coordinates: at most 1e-5
    voxel off on a 256-voxel axis). ``rows_per_chunk``: slab height (default: about :data:`SLAB_VOXELS` voxels per
    slab).
    """
    moving_grid = np.asarray(moving_index_to_lps, np.float64)
    moving_to_fixed = np.linalg.inv(np.asarray(affine, np.float64)) @ moving_grid
    to_field_index = np.linalg.inv(np.asarray(inverse_mm.index_to_lps, np.float64)) @ moving_to_fixed
    field = np.asarray(inverse_mm.array, dtype=np.float32)
    # index -> grid_sample's normalised coordinate, rows in its (x, y, z) order (blocks.grid_coords)
    normalise = index_to_grid_matrix([int(n) for n in field.shape[:3]]).numpy() @ to_field_index
    shift = moving_to_fixed - moving_grid  # a - q, affine in the index
    source = torch.from_numpy(np.ascontiguousarray(field.transpose(3, 0, 1, 2)))[None]
    shape = tuple(int(n) for n in moving_shape)
    rows = rows_per_chunk or max(1, SLAB_VOXELS // max(1, shape[1] * shape[2]))
    out = torch.empty((*shape, 3), dtype=torch.float32)
    for start in range(0, shape[0], rows):
        slab = (min(rows, shape[0] - start), *shape[1:])
        to_slab = np.eye(4)
        to_slab[0, 3] = start  # slab index (r, j, k) -> moving index (start + r, j, k)
        grid = torch.from_numpy(index_map(slab, normalise @ to_slab)).float()
        values = split_grid_sample(source, grid[None], mode="bilinear", padding_mode="border")[0]  # all threads
        out[start : start + slab[0]] = values.permute(1, 2, 3, 0) + torch.from_numpy(index_map(slab, shift @ to_slab))
    return out.numpy()


def affine_to_itk(matrix: np.ndarray, center: np.ndarray | None = None) -> itk.AffineTransform:
    """(4, 4) LPS matrix -> ``itk.AffineTransform[itk.D, 3]`` with the given centre of rotation (default origin)."""
    transform = itk.AffineTransform[itk.D, 3].New()
    center = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    transform.SetCenter([float(c) for c in center])
    transform.SetMatrix(itk.matrix_from_array(np.ascontiguousarray(matrix[:3, :3], dtype=np.float64)))
    # T(p) = M (p - c) + c + t = M p + offset  =>  t = offset - c + M c
    translation = matrix[:3, 3] - center + matrix[:3, :3] @ center
    transform.SetTranslation([float(t) for t in translation])
    return transform


def affine_from_itk(transform: itk.Transform) -> np.ndarray:
    """Any ITK matrix-offset transform (Euler, versor, affine) -> its (4, 4) LPS matrix ``[[M, offset], [0, 1]]``."""
    matrix = np.eye(4)
    matrix[:3, :3] = itk.array_from_matrix(transform.GetMatrix())
    matrix[:3, 3] = np.asarray(transform.GetOffset(), dtype=np.float64)
    return matrix


def field_to_itk(field: np.ndarray, index_to_lps: np.ndarray) -> itk.Image:
    """A displacement field (*S, 3) LPS mm on the grid ``index_to_lps`` -> ``itk.Image[itk.Vector[itk.F, 3], 3]``
    (float32: the type ITK's Python wrapping reads and writes, and what ANTs' warp files hold)."""
    array = np.ascontiguousarray(np.asarray(field, dtype=np.float32).transpose(2, 1, 0, 3))
    image = itk.image_from_array(array, ttype=itk.Image[itk.Vector[itk.F, 3], 3])
    spacing = np.linalg.norm(index_to_lps[:3, :3], axis=0)
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(o) for o in index_to_lps[:3, 3]])
    image.SetDirection(itk.matrix_from_array(np.ascontiguousarray(index_to_lps[:3, :3] / spacing)))
    return image


def field_from_itk(image: itk.Image) -> Volume:
    """An ITK vector image (e.g. ``itk.imread("warp.nii.gz")``) -> :class:`Volume` with array (*S, 3), float64."""
    from monai_probreg.spatial.volume_io import geometry_of

    array = np.asarray(itk.array_from_image(image), dtype=np.float64).transpose(2, 1, 0, 3)
    return Volume(np.ascontiguousarray(array), geometry_of(image))


def displacement_transform(field: itk.Image) -> itk.DisplacementFieldTransform:
    """``itk.DisplacementFieldTransform[itk.D, 3]`` of a vector field image (as written to ``warp.nii.gz``).

    ``itk.ResampleImageFilter`` takes double-precision transforms, and ITK's Python wrapping has no reader for
    double vector images, so the float field is copied into an ``itk.Image[itk.Vector[itk.D, 3], 3]``.
    """
    double = itk.Image[itk.Vector[itk.D, 3], 3].New()
    double.SetRegions(field.GetLargestPossibleRegion())
    double.SetSpacing(field.GetSpacing())
    double.SetOrigin(field.GetOrigin())
    double.SetDirection(field.GetDirection())
    double.Allocate()
    itk.array_view_from_image(double)[...] = itk.array_view_from_image(field)
    transform = itk.DisplacementFieldTransform[itk.D, 3].New()
    transform.SetDisplacementField(double)
    return transform


def resample_with_itk(
    moving: itk.Image, reference: itk.Image, transform: itk.Transform, nearest: bool = False
) -> itk.Image:
    """ITK's own resampling of ``moving`` onto ``reference``'s grid through ``transform`` (fixed -> moving),
    linear or nearest neighbour, 0 outside: what ``antsApplyTransforms -i moving -r reference -t ...`` does.
    The independent check of our outputs (tests, ``benchmarks/register_real_scan.py``)."""
    image_type = type(moving)
    interpolator = itk.NearestNeighborInterpolateImageFunction if nearest else itk.LinearInterpolateImageFunction
    resampler = itk.ResampleImageFilter[image_type, image_type].New(
        Input=moving,
        Transform=transform,
        Interpolator=interpolator[image_type, itk.D].New(),
        UseReferenceImage=True,
        ReferenceImage=reference,
        DefaultPixelValue=0,
    )
    resampler.Update()
    return resampler.GetOutput()
