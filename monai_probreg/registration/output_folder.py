"""The output folder of one registration (``monai-probreg register``'s ``DIR``): all-or-nothing writing, ITK
writers, the writer of each file of a registration (:func:`output_writers`) and the QC figure's slices
(:func:`network_qc_planes`, :func:`finished_qc_planes`, drawn by :mod:`.qc`). What each file is: :mod:`.output_files` (``README.txt``).

All-or-nothing: every file is written into a hidden staging folder next to ``DIR`` (same file system) and moved
into ``DIR`` only when the whole registration has succeeded (:func:`staged_output_dir`). On any error, including
Ctrl-C, the staging folder is removed and ``DIR`` is left as it was; a hard kill can leave a hidden
``.DIR.partial-*`` folder next to ``DIR``, never a half-written file inside it.

Images and fields are written with the header ITK writes (ITK is the reader ANTs and Slicer use), so they carry
exactly the geometry ITK read from the inputs: NIfTI by :mod:`monai_probreg.spatial.nifti_write` (nibabel and
ISA-L's gzip, far faster than ITK's writer), other formats by ITK; each write is itself atomic
(:func:`monai_probreg.utils.files.atomic_write`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import itk
import numpy as np

from monai_probreg.registration.compose import Composed
from monai_probreg.registration.inputs import FixedSpace, label_dtype
from monai_probreg.registration.network import ModelMaps
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_files import OUTPUT_FILES
from monai_probreg.registration.qc import QCData, QCPlanes, qc_planes
from monai_probreg.registration.quality_estimate import ScanQuality
from monai_probreg.spatial.affine import AffineResult
from monai_probreg.spatial.checks import is_nifti
from monai_probreg.spatial.nifti_write import write_nifti
from monai_probreg.spatial.physical import field_to_itk
from monai_probreg.spatial.volume_io import Volume, volume_to_itk
from monai_probreg.utils.errors import InputError
from monai_probreg.utils.files import atomic_write, write_text

__all__ = [
    "MAP_FILES",
    "check_output_dir",
    "staged_output_dir",
    "write_volume",
    "label_dtype",
    "write_field",
    "write_transform",
    "output_writers",
    "network_qc_planes",
    "finished_qc_planes",
    "qc_title",
]


def check_output_dir(out_dir: str | os.PathLike, overwrite: bool = False) -> Path:
    """InputError if ``out_dir`` is a file, an existing non-empty folder (unless ``overwrite``), or not writable.
    Missing parent folders are fine (created when the outputs are moved into place)."""
    path = Path(out_dir)
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {str(path)!r}: exists and is a file, not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise InputError(
            f"--out {str(path)!r}: folder exists and is not empty; pass --overwrite to replace its "
            "outputs, or choose another folder"
        )
    existing = path
    while not existing.exists():  # nearest existing folder: where the new ones will be created
        existing = existing.parent
    if not os.access(existing, os.W_OK):
        raise InputError(f"--out {str(path)!r}: no permission to write in {str(existing)!r}")
    return path


@contextmanager
def staged_output_dir(out_dir: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a staging folder; on success move its files into ``out_dir`` (module docstring), else delete it.

    With ``overwrite``, files of ours (:data:`~.output_files.OUTPUT_FILES`) left from an earlier run and not produced by this one
    are removed, so the folder never mixes two runs; files of other names are kept.
    """
    final = check_output_dir(out_dir, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    stage = final.parent / f".{final.name}.partial-{uuid.uuid4().hex[:8]}"
    stage.mkdir()
    try:
        yield stage
        if not final.exists():
            os.rename(stage, final)  # atomic: DIR appears complete
            return
        produced = {p.name for p in stage.iterdir()}
        for name in OUTPUT_FILES:
            if name not in produced and (final / name).is_file():
                (final / name).unlink()
        for item in stage.iterdir():
            os.replace(item, final / item.name)
        stage.rmdir()
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)


def write_volume(path: str | os.PathLike, volume: Volume, dtype: type = np.float32) -> Path:
    """Write a :class:`Volume` (atomic); labels: pass an integer ``dtype`` (int16 when it fits). NIfTI through
    :mod:`monai_probreg.spatial.nifti_write` (ITK's header, compressed faster), other formats with ITK."""
    if is_nifti(path):
        return write_nifti(path, volume.array.astype(dtype, copy=False), volume.index_to_lps)
    image = volume_to_itk(volume, dtype)
    return atomic_write(path, lambda tmp: itk.imwrite(image, tmp, compression=True))


def write_field(path: str | os.PathLike, field: np.ndarray, index_to_lps: np.ndarray) -> Path:
    """Write a displacement field (*S, 3) in LPS mm as an ITK vector image (NIfTI intent "vector", float32)."""
    if is_nifti(path):
        return write_nifti(path, np.asarray(field, dtype=np.float32), index_to_lps, vector=True)
    image = field_to_itk(field, index_to_lps)
    return atomic_write(path, lambda tmp: itk.imwrite(image, tmp, compression=True))


def write_transform(path: str | os.PathLike, matrix: np.ndarray, center: np.ndarray | None = None) -> Path:
    """Write an affine map (4, 4; fixed LPS -> moving LPS) as ITK's text transform file, atomically:
    ``AffineTransform_double_3_3`` with its 12 parameters (matrix row by row, translation) about ``center`` (LPS mm,
    default the origin; ITK's ``FixedParameters``: the map is the same for any centre).

    Written as text here, not with ``itk.transformwrite``: ITK's transform writer loads every wrapped transform
    type on first use (about 6 s, more than the rest of the writing), for a file of five lines in ITK's
    documented ``#Insight Transform File V1.0`` format. Read back by ``itk.transformread`` and ANTs (tested)."""
    if Path(path).suffix not in (".tfm", ".txt"):
        raise ValueError(f"expected a .tfm or .txt path (ITK's text transform format); got {str(path)!r}")
    matrix = np.asarray(matrix, dtype=np.float64)
    center = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    translation = matrix[:3, 3] - center + matrix[:3, :3] @ center  # T(p) = M (p - c) + c + t
    numbers = [*matrix[:3, :3].reshape(-1), *translation]
    if not np.isfinite([*numbers, *center]).all():
        raise ValueError(f"{str(path)!r}: the transform has non-finite parameters {numbers}, centre {center.tolist()}")
    text = (
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        f"Parameters: {' '.join(repr(float(v)) for v in numbers)}\n"
        f"FixedParameters: {' '.join(repr(float(v)) for v in center)}\n"
    )
    return write_text(path, text)


MAP_FILES = ("jacobian", "entropy", "displacement_std")  # left out by RegistrationOptions.maps = False


def output_writers(
    stage: Path,
    fixed: FixedSpace,
    moving: Volume,
    affine: AffineResult,
    composed: Composed,
    options: RegistrationOptions,
) -> list[Callable[[], object]]:
    """One call per output file (run in parallel by :func:`~monai_probreg.utils.files.parallel_writes`), largest
    first so that the pool's last file is a small one; but one call for both displacement fields, which writes them
    one after the other (:func:`_in_turn`): each holds its uncompressed and its compressed file while it is written
    (:mod:`monai_probreg.spatial.nifti_write`), the largest of all the files, so two at once would hold both."""
    fields = []
    if composed.inverse_warp is not None:
        fields.append(
            functools.partial(write_field, stage / "inverse_warp.nii.gz", composed.inverse_warp, moving.index_to_lps)
        )
    fields.append(functools.partial(write_field, stage / "warp.nii.gz", composed.warp, fixed.image.index_to_lps))
    field_size = composed.warp.size + (0 if composed.inverse_warp is None else composed.inverse_warp.size)
    writers: list[tuple[int, Callable[[], object]]] = [(field_size, functools.partial(_in_turn, fields))]
    for name, array in composed.maps.items():
        if options.maps or name not in MAP_FILES:
            writers.append(
                (
                    array.size,
                    functools.partial(
                        write_volume,
                        stage / f"{name}.nii.gz",
                        fixed.image.with_array(array.astype(np.float32, copy=False)),
                    ),
                )
            )
    for name, grid in (("warped_label", fixed.image), ("fixed_label_in_moving", moving)):
        if name in composed.labels:
            array = composed.labels[name]
            writers.append(
                (
                    array.size // 4,
                    functools.partial(  # bytes, roughly: 1-2 per label voxel, 4 per float
                        write_volume, stage / f"{name}.nii.gz", grid.with_array(array), label_dtype(array)
                    ),
                )
            )
    writers.append((0, functools.partial(write_transform, stage / "affine.tfm", affine.matrix, affine.center)))
    return [write for _, write in sorted(writers, key=lambda item: -item[0])]


def _in_turn(writers: list[Callable[[], object]]) -> None:
    """Run ``writers`` one after the other, each let go once it has run (and with it the array it wrote, when it
    held the last reference)."""
    while writers:
        writers.pop(0)()


def network_qc_planes(fixed: FixedSpace, moving_input: np.ndarray, model_maps: ModelMaps) -> QCPlanes:
    """The QC figure's slices (:mod:`.qc`) of the images, the network's maps and the fixed labels on the model grid;
    the resampled labels, the title and the warning come later (:func:`finished_qc_planes`)."""
    sampled = model_maps.std is not None
    return qc_planes(
        QCData(
            fixed=fixed.model_input,
            moving=moving_input,
            warped=model_maps.warped,
            displacement=model_maps.displacement,
            jacobian=model_maps.jacobian,
            uncertainty=model_maps.std if sampled else model_maps.entropy,
            uncertainty_name="displacement std (mm)" if sampled else "velocity entropy",
            spacing=tuple(fixed.grid.spacing),
            fixed_label=fixed.grid.to_model(fixed.label.array) if fixed.label is not None else None,
        )
    )


def finished_qc_planes(
    planes: QCPlanes, fixed: FixedSpace, composed: Composed, title: str, warning: str | None = None
) -> QCPlanes:
    """``planes`` (:func:`network_qc_planes`) with the moving labels' slices (through the affine, and warped), the
    title and the warning."""
    to_model, labels = fixed.grid.to_model, composed.labels
    planes = planes.with_labels(
        moving_label=to_model(labels["affine_label"]) if "affine_label" in labels else None,
        warped_label=to_model(labels["warped_label"]) if "warped_label" in labels else None,
    )
    return dataclasses.replace(planes, title=title, warning=warning)


def qc_title(
    moving: Volume,
    dice: dict | None,
    num_folding: int,
    quality: ScanQuality | None,
) -> str:
    """The QC figure's title: the scan, its Dice (with labels), the folding count, the predicted Dice."""
    title = Path(moving.path).name + (
        f"   mean Dice {dice['mean']:.3f} (affine only {dice['mean_affine_only']:.3f})" if dice else ""
    )
    title += f"   |J| <= 0: {num_folding} voxels"
    if quality is not None:
        title += f"   predicted Dice {quality.estimate.predicted_dice:.2f}"
    return title
