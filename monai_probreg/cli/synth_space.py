"""Whole-head label maps moved into a template's space: synthetic training subjects from other anatomies.

Training on one dataset teaches the network that dataset's anatomy (issue "Beyond LPBA40"). Label maps of other
heads (FreeSurfer labels, e.g. the SynthSeg repository's ``training_label_maps``) become training subjects here,
through the code path users' scans take to the default template:

1. each label map is rendered as a T1-like whole head at its own resolution
   (:func:`monai_probreg.data.label_synthesis.render_labels`, one fixed table per map: skull and scalp kept), so the
   affine stage sees what it sees in a user's raw scan;
2. the affine stage of ``register`` aligns it to the template (MNI152 by default);
3. the rendered image and the label map are resampled onto the template grid (linear / nearest) and, as the command
   does, hidden outside the template's brain mask (:mod:`monai_probreg.spatial.brain_mask`).

The folder written has the layout of :func:`monai_probreg.data.dataset.index_dataset` (``images/``, ``labels/``, and
``atlas/`` holding the template, without labels). Training re-renders each pair from the labels with random
contrasts (``bundle/configs/train_synth.yaml``); the written images serve the affine stage and inspection. Usage:

    python -m monai_probreg.cli.synth_space --label-maps DIR --out-dir runs/synth_mni \\
        --ids training_seg_01 ... training_seg_10
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from monai_probreg.data.label_synthesis import T1_LIKE, render_labels
from monai_probreg.data.template import mni152_template_path
from monai_probreg.registration.inputs import prepare_fixed
from monai_probreg.registration.output_folder import label_dtype, write_volume
from monai_probreg.spatial.affine import AffineSettings, align
from monai_probreg.spatial.brain_mask import hide_outside
from monai_probreg.spatial.physical import mapped_index
from monai_probreg.spatial.point_sampling import sample_linear, sample_nearest
from monai_probreg.spatial.volume_io import Volume, read_label
from monai_probreg.utils.files import file_stem

__all__ = ["RENDER_BLUR_VOXELS", "RENDER_TEXTURE", "SYNTH_ATLAS_NAME", "render_head", "to_synth_space"]

SYNTH_ATLAS_NAME = "template"  # atlas/<name>_image.nii.gz: the template the subjects were moved to
RENDER_TEXTURE = 0.03  # texture noise of the affine stage's rendering (the table's units: white matter = 1)
RENDER_BLUR_VOXELS = 0.6  # its partial-volume blur, voxels of the label map

_LOG = logging.getLogger("monai_probreg.synth_space")


def render_head(labels: Volume, seed: int = 0, brain: Mapping[int, float] = T1_LIKE) -> Volume:
    """A rendering of a label map on its own grid: the brain by ``brain`` (T1-like by default; :data:`T2_LIKE` for a
    T2-weighted look), every other label (skull, scalp, eyes...) at a random intensity drawn from ``seed``; float32 in
    [0, 1]."""
    values = np.unique(labels.array)
    rng = np.random.default_rng(seed)
    table = {int(v): brain.get(int(v), float(rng.uniform())) for v in values if v > 0}
    generator = torch.Generator().manual_seed(seed)
    image = render_labels(
        torch.from_numpy(labels.array.astype(np.int64))[None], table, RENDER_TEXTURE, RENDER_BLUR_VOXELS, generator
    )[0]
    return labels.with_array(image.numpy().astype(np.float32))


def to_synth_space(
    label_maps: list[Path],
    out_dir: str | os.PathLike,
    template: str | os.PathLike | None = None,
    affine: AffineSettings | None = None,
    seed: int = 0,
) -> Path:
    """Write the dataset folder of the module docstring for ``label_maps`` (ids: their file stems); returns it."""
    if not label_maps:
        raise ValueError("expected at least one label map; got none")
    template_path = Path(template) if template is not None else mni152_template_path()
    out = Path(out_dir)
    for sub in ("images", "labels", "atlas"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    fixed = prepare_fixed(template_path)
    settings = affine or AffineSettings()
    for n, path in enumerate(label_maps, start=1):
        sid = file_stem(path)
        labels = read_label(path, sid)
        head = render_head(labels, seed + n)
        result = align(
            fixed.image,
            head,
            settings,
            fixed.itk_image if settings.backend == "itk" else None,
            fixed.samples_for(settings),
        )
        index = mapped_index(fixed.image.shape, fixed.image.index_to_lps, head.index_to_lps, result.matrix)
        image = hide_outside(sample_linear(head, None, fill=0.0, index=index).astype(np.float32), fixed.brain_mask, 0.0)
        label = hide_outside(sample_nearest(labels, None, index=index), fixed.brain_mask, 0)
        write_volume(out / "images" / f"{sid}.nii.gz", fixed.image.with_array(image))
        write_volume(out / "labels" / f"{sid}.nii.gz", fixed.image.with_array(label), label_dtype(label))
        _LOG.info(f"{n}/{len(label_maps)} {sid}: affine metric {result.stages[-1].metric:.4f}")
    suffix = ".nii.gz" if template_path.name.endswith(".nii.gz") else template_path.suffix
    shutil.copyfile(template_path, out / "atlas" / f"{SYNTH_ATLAS_NAME}_image{suffix}")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--label-maps", required=True, help="a folder of whole-head label maps (FreeSurfer labels)")
    parser.add_argument("--out-dir", required=True, help="the folder written (keep it out of the repository)")
    parser.add_argument(
        "--ids",
        nargs="+",
        required=True,
        help="file stems of the label maps to move (name them: held-out maps stay out)",
    )
    parser.add_argument("--template", default=None, help="the fixed image (default: the MNI152 template of nilearn)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the renderings' random intensities")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    folder = Path(args.label_maps)
    found = {file_stem(p): p for p in folder.glob("*.nii*")}
    missing = [i for i in args.ids if i not in found]
    if missing:
        parser.error(f"--ids {missing} are not in {folder} (have {sorted(found)})")
    out = to_synth_space([found[i] for i in args.ids], args.out_dir, args.template, seed=args.seed)
    print(f"wrote {out} ({len(args.ids)} subjects and the template)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
