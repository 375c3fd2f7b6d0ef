"""``monai-probreg apply``: a displacement field or an affine file applied to any image or label map.

``antsApplyTransforms -t FIELD -i IMAGE -r GRID -o OUT -n Linear|NearestNeighbor`` with one transform: the output
lies on the reference grid (its shape and header) and each of its voxels ``p`` shows the moving image at ``T(p)``
(:mod:`monai_probreg.spatial.transform_files`: ``p + D(p)`` for a field, ITK's interpolation of the field and its 0
outside the field's grid). Through ``register``'s own ``warp.nii.gz`` onto its ``--fixed`` image, ``--interpolation
nearest`` of its ``--moving-label`` gives ``warped_label.nii.gz`` and linear of its ``--moving`` ``warped.nii.gz``,
byte for byte (the same sampling code, at the same points, written by the same writer).

Output type: with ``nearest``, a moving image of non-negative integers (a label map, or integer intensities) keeps
an integer type (the smallest of uint8 / int16 / int32 that holds it, as ``register`` writes labels), anything else
float32; with ``linear``, float32. Bad input: one line naming the file and the problem, exit status 1, nothing
written (the output is checked before anything is read and written atomically at the end).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

__all__ = ["APPLY_DESCRIPTION", "INTERPOLATIONS", "OUTPUT_SUFFIXES", "add_apply_parser", "apply_transform_file"]

INTERPOLATIONS = ("linear", "nearest")
OUTPUT_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".mha")  # single-file formats: written atomically
_ANTS_NAMES = {"nearestneighbor": "nearest"}  # antsApplyTransforms' spelling of ours

APPLY_DESCRIPTION = """\
Apply a transform to any image or label map, as antsApplyTransforms -t FIELD -i IMAGE -r GRID -o OUT does: the
output lies on GRID's grid (its shape and header) and shows IMAGE at p + D(p) for each of its points p, D being
the field (LPS mm, ITK/ANTs convention). FIELD: register's warp.nii.gz (GRID: its --fixed image) or
inverse_warp.nii.gz (GRID: its --moving scan), any ITK/ANTs displacement field (interpolated linearly where its
grid is not GRID's, identity outside it, as ITK does), or one affine (.tfm/.txt ITK text, ANTs .mat).

  monai-probreg apply --transform results/sub01/warp.nii.gz --moving sub01_t2.nii.gz \\
      --reference atlas.nii.gz --out sub01_t2_in_atlas.nii.gz
  monai-probreg apply -t results/sub01/inverse_warp.nii.gz -i atlas_seg.nii.gz -r sub01.nii.gz \\
      -o atlas_seg_in_sub01.nii.gz -n nearest

--interpolation nearest of register's --moving-label through its warp.nii.gz onto its --fixed image gives its
warped_label.nii.gz exactly. Output: integer labels keep an integer type with nearest; float32 otherwise.
Exit status: 0 on success; 1 with one line "monai-probreg: error: <file>: <problem>" and nothing written; 2 for a
malformed command line.
"""


def add_apply_parser(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``apply`` subcommand's parser, added to ``commands``."""
    parser = commands.add_parser(
        "apply",
        help="apply warp.nii.gz (or any ITK/ANTs field or affine) to an image or label map",
        description=APPLY_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "-t",
        "--transform",
        required=True,
        metavar="FIELD",
        help="displacement field (warp.nii.gz, inverse_warp.nii.gz, an ANTs *Warp.nii.gz: a vector image, LPS mm, "
        "output point -> input point) or one affine file (.tfm/.txt ITK text, ANTs .mat)",
    )
    parser.add_argument("-i", "--moving", required=True, metavar="IMAGE", help="the image or label map to resample")
    parser.add_argument(
        "-r",
        "--reference",
        required=True,
        metavar="GRID",
        help="any image (or a displacement field) whose grid (shape, spacing, orientation, origin) the output takes",
    )
    parser.add_argument(
        "-o",
        "--out",
        required=True,
        metavar="OUT",
        help=f"output image ({', '.join(OUTPUT_SUFFIXES)}; missing folders are created)",
    )
    parser.add_argument(
        "-n",
        "--interpolation",
        type=lambda name: _ANTS_NAMES.get(name.lower(), name.lower()),
        choices=INTERPOLATIONS,
        default="linear",
        help="linear (default: images, float32 out) or nearest (label maps: integer labels keep an integer type)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    parser.add_argument("--threads", type=int, default=None, metavar="N", help="CPU threads (default: all)")
    parser.add_argument(
        "--max-voxels",
        type=int,
        default=None,
        metavar="N",
        help="refuse an image of more than N voxels before reading it (default: $MONAI_PROBREG_MAX_VOXELS, else 512^3)",
    )
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an unexpected error")
    return parser


def check_output_file(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """InputError unless ``out`` is a new (or, with ``overwrite``, an existing) image file of
    :data:`OUTPUT_SUFFIXES` that can be written: its folder, or the nearest existing one above it, writable."""
    from monai_probreg.registration.output_folder import check_output_dir
    from monai_probreg.utils.errors import InputError

    path = Path(out)
    where = f"--out {str(path)!r}"
    if path.is_dir():
        raise InputError(f"{where}: is a folder; expected the output image's file name")
    if not path.name.lower().endswith(OUTPUT_SUFFIXES):
        raise InputError(f"{where}: expected an image file name ending in {', '.join(OUTPUT_SUFFIXES)}")
    if path.exists() and not overwrite:
        raise InputError(f"{where}: exists; pass --overwrite to replace it, or choose another name")
    check_output_dir(path.parent, overwrite=True)  # a file where its folder should be; no permission to write
    return path


def _read_moving(path: str | os.PathLike, nearest: bool):
    """The moving image: float32 for linear; for nearest, int32 when it holds non-negative integers (then written as
    a label map is), else float32."""
    import numpy as np

    from monai_probreg.spatial.volume_io import read_volume

    if not nearest:
        return read_volume(path, "--moving", np.float32)
    volume = read_volume(path, "--moving", np.float64)  # integers exact up to 2^53, as read_label reads them
    values = volume.array
    if values.min() >= 0 and values.max() <= np.iinfo(np.int32).max and np.array_equal(values, np.round(values)):
        return volume.with_array(values.astype(np.int32))
    return volume.with_array(values.astype(np.float32))


def _read_reference(path: str | os.PathLike):
    """The reference grid: a scalar image's, or a displacement field's own (``-r warp.nii.gz``, as ANTs takes any
    image); a file that is neither gets the scalar reader's one line."""
    import numpy as np

    from monai_probreg.spatial.volume_io import read_field, read_volume
    from monai_probreg.utils.errors import InputError

    try:
        return read_volume(path, "--reference", np.float32)
    except InputError as scalar_error:
        try:
            return read_field(path, "--reference")
        except InputError:
            raise scalar_error from None


def apply_transform_file(
    transform: str | os.PathLike,
    moving: str | os.PathLike,
    reference: str | os.PathLike,
    out: str | os.PathLike,
    interpolation: str = "linear",
    overwrite: bool = False,
) -> tuple[Path, float]:
    """Resample ``moving`` onto ``reference``'s grid through ``transform`` and write ``out`` (module docstring).
    Returns (the written path, the fraction of the reference grid inside the field's grid: 1.0 for an affine).
    Raises :class:`~monai_probreg.utils.errors.InputError` (one line) before anything is written."""
    import numpy as np

    from monai_probreg.registration.output_folder import label_dtype, write_volume
    from monai_probreg.spatial.transform_files import read_transform, resample_through

    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}; got {interpolation!r}")
    path = check_output_file(out, overwrite)
    nearest = interpolation == "nearest"
    field = read_transform(transform, "--transform")
    image = _read_moving(moving, nearest)
    grid = _read_reference(reference)
    resampled = resample_through(image, grid, field, nearest)
    integer = np.issubdtype(resampled.array.dtype, np.integer)
    dtype = label_dtype(resampled.array) if integer else np.float32
    return write_volume(path, grid.with_array(resampled.array), dtype), resampled.field_coverage


def run_apply(args: argparse.Namespace) -> int:
    """``monai-probreg apply`` (the parsed arguments of :func:`add_apply_parser`): write, print one line; 0."""
    if args.threads is not None:
        import torch

        from monai_probreg.utils.errors import InputError

        if args.threads < 1:
            raise InputError(f"--threads must be >= 1; got {args.threads}")
        torch.set_num_threads(args.threads)
        os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)
    path, coverage = apply_transform_file(
        args.transform, args.moving, args.reference, args.out, args.interpolation, args.overwrite
    )
    if coverage < 1.0:
        print(
            f"monai-probreg: warning: --transform {args.transform!r}: {100 * (1 - coverage):.1f}% of the reference "
            "grid lies outside the field's grid, where the displacement is 0 (identity, as in ITK and ANTs); is "
            "--reference the image the field was computed on?",
            file=sys.stderr,
        )
    print(f"{path}: {args.moving} through {args.transform} onto the grid of {args.reference} ({args.interpolation})")
    return 0
