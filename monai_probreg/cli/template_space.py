"""A dataset moved into a template's space: training data for the grid users register to by default.

``monai-probreg register`` without ``--fixed`` registers onto the MNI152 template nilearn ships
(:mod:`monai_probreg.data.template`): a 197 x 233 x 189 grid of 1 mm whose brain is larger than LPBA40's and which the
network sees at another scale (2.4-2.6 template voxels per network voxel, LPBA40 2). A network trained on the LPBA40
grid alone has never seen that grid, nor the template's smooth, averaged contrast (issue "Robust to the scans users
bring", lever "the MNI template as an extra fixed image"). This module writes a dataset folder in the template's space
(the layout of :func:`monai_probreg.data.dataset.index_dataset`), through the code path of ``register``:

- ``images/<id>.nii.gz``, ``labels/<id>.nii.gz``: every subject after the **affine stage alone** (linear / nearest
  resampling onto the template grid): what the network sees when a user registers that scan to the template.
- ``atlas/<name>_image.nii.gz``: the template itself; ``atlas/<name>_label.nii.gz``: a label map for it, the
  voxel-wise majority vote of the subjects' labels after the **whole** registration (affine + the given weights;
  multi-atlas label fusion), so the label term of semi-supervised training also applies to pairs with the template.

The folder holds images derived from the dataset's voxels: keep it out of the repository (``runs/``). Usage:

    python -m monai_probreg.cli.template_space --dataset-dir ../shared/data/lpba40 --out-dir runs/lpba40_mni \\
        --exclude S11 S14 S16 S21 S28 S29
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

from monai_probreg.data.dataset import index_dataset
from monai_probreg.data.template import mni152_template_path
from monai_probreg.engines.refinement import RefinementSettings
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.model import load_model
from monai_probreg.registration.options import RegistrationOptions
from monai_probreg.registration.output_folder import label_dtype, write_volume
from monai_probreg.registration.scan import Registered, register_scan
from monai_probreg.spatial.affine import AffineSettings
from monai_probreg.spatial.physical import mapped_index
from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
from monai_probreg.spatial.volume_io import Volume, read_image, read_label

__all__ = ["TEMPLATE_ATLAS_NAME", "majority_vote", "to_template_space"]

TEMPLATE_ATLAS_NAME = "template"  # atlas/<name>_image.nii.gz and _label.nii.gz in the folder written

_LOG = logging.getLogger("monai_probreg.template_space")


def majority_vote(label_maps: list[np.ndarray]) -> np.ndarray:
    """Voxel-wise most frequent value of integer maps of one shape (ties: the smaller value; 0 counts as a label)."""
    if not label_maps:
        raise ValueError("majority_vote needs at least one label map; got none")
    shape = label_maps[0].shape
    bad = [m.shape for m in label_maps if m.shape != shape]
    if bad:
        raise ValueError(f"label maps must share one shape; expected {shape}, got {bad[0]}")
    values = np.unique(np.concatenate([np.unique(m) for m in label_maps]))
    best = np.full(shape, values[0], dtype=label_maps[0].dtype)
    best_count = np.zeros(shape, dtype=np.int32)
    for value in values:  # ascending: a later value must count strictly more to win, so ties keep the smaller one
        count = np.zeros(shape, dtype=np.int32)
        for m in label_maps:
            count += m == value
        wins = count > best_count
        best[wins], best_count[wins] = value, count[wins]
    return best


def _affine_only(
    registered: Registered, fixed: Volume, moving: Volume, moving_label: Volume
) -> tuple[np.ndarray, np.ndarray]:
    """The moving scan and its labels on the fixed grid through the affine stage alone (the command's resampling)."""
    index = mapped_index(fixed.shape, fixed.index_to_lps, moving.index_to_lps, registered.affine)
    return (
        sample_linear(moving, None, fill=float(moving.array.min()), index=index).astype(np.float32),
        sample_nearest(moving_label, None, index=index),
    )


def to_template_space(
    dataset_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    ids: list[str] | None = None,
    template: str | os.PathLike | None = None,
    model_file: str | os.PathLike | None = None,
    bundle_root: str | os.PathLike | None = None,
    affine: AffineSettings | None = None,
) -> Path:
    """Write the dataset folder of the module docstring for the labelled subjects ``ids`` (default all); returns it.
    ``template``: the fixed image (default the MNI152 template); ``model_file``, ``bundle_root``: the weights of the
    label fusion's registrations (default the bundle's); ``affine``: the affine stage's settings (default the
    command's)."""
    index = index_dataset(dataset_dir)
    chosen = [i for i in (ids if ids is not None else index.ids) if i in index.labels]
    if not chosen:
        raise ValueError(f"no labelled subject to move among {ids if ids is not None else index.ids}")
    template_path = Path(template) if template is not None else mni152_template_path()
    out = Path(out_dir)
    for sub in ("images", "labels", "atlas"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    model = load_model(bundle_root, model_file, quality=False)
    fixed = prepare_fixed(template_path)
    # the network alone, as when the shipped weights' template-space data was made (refinement=None would refine)
    options = RegistrationOptions(
        qc=False, inverse=False, maps=False, affine=affine or AffineSettings(), refinement=RefinementSettings()
    )
    fused_inputs, captured = [], []

    def keep(registered: Registered) -> dict:  # register_scan's check: keeps the affine, adds nothing to the summary
        captured.append(registered)
        return {}

    with tempfile.TemporaryDirectory() as scratch:
        for n, sid in enumerate(chosen, start=1):
            moving, moving_label = read_image(index.images[sid], sid), read_label(index.labels[sid], sid)
            summary = register_scan(model, fixed, moving, Path(scratch) / sid, index.labels[sid], options, check=keep)
            image, label = _affine_only(captured[-1], fixed.image, moving, moving_label)
            write_volume(out / "images" / f"{sid}.nii.gz", fixed.image.with_array(image))
            write_volume(out / "labels" / f"{sid}.nii.gz", fixed.image.with_array(label), label_dtype(label))
            fused_inputs.append(read_label(Path(scratch) / sid / "warped_label.nii.gz", sid).array)
            shutil.rmtree(Path(scratch) / sid)
            _LOG.info(
                f"{n}/{len(chosen)} {sid}: {summary['timings_s']['total']:.1f} s, folded voxels "
                f"{summary['jacobian']['num_nonpositive']}"
            )
    fused = majority_vote(fused_inputs)
    shutil.copyfile(template_path, out / "atlas" / f"{TEMPLATE_ATLAS_NAME}_image{_suffix(template_path)}")
    write_volume(
        out / "atlas" / f"{TEMPLATE_ATLAS_NAME}_label.nii.gz", fixed.image.with_array(fused), label_dtype(fused)
    )
    return out


def _suffix(path: Path) -> str:
    return ".nii.gz" if path.name.endswith(".nii.gz") else path.suffix


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset-dir", required=True, help="a dataset folder (atlas/, images/, labels/)")
    parser.add_argument("--out-dir", required=True, help="the folder written (keep it out of the repository)")
    parser.add_argument("--ids", nargs="*", default=None, help="subjects to move (default: all labelled ones)")
    parser.add_argument("--exclude", nargs="*", default=[], help="subjects left out (e.g. the validation subjects)")
    parser.add_argument("--template", default=None, help="the fixed image (default: the MNI152 template of nilearn)")
    parser.add_argument("--model-file", default=None, help="weights of the label fusion (default: the bundle's)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    ids = args.ids if args.ids is not None else index_dataset(args.dataset_dir).ids
    ids = [i for i in ids if i not in set(args.exclude)]
    out = to_template_space(args.dataset_dir, args.out_dir, ids, args.template, args.model_file)
    print(f"wrote {out} ({len(ids)} subjects and the template)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
