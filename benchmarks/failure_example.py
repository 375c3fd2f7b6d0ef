"""A flagged failure beside a normal case, as a user meets them: the README picture of "when to distrust a
registration".

The scan is the MNI152 template nilearn ships (no LPBA40 voxel in the picture), moved out of place by a known rigid
transform (seeded) and resampled as a raw scan; it is registered onto the template (the command's default fixed
image) twice with the whole command: as it is, and with its orientation header turned by 180 degrees about S (the
voxels untouched). The two QC figures are put one above the other in ``failure_example.png``; the summaries' quality
estimates are printed.

    python benchmarks/failure_example.py --threads 2     # -> benchmarks/results/failure_example.png
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from common import DEFAULT_OUT, run_command
from register_real_scan import misalign

from monai_probreg.data.template import mni152_template_path
from monai_probreg.fitting.command_cases import turned_header
from monai_probreg.registration.output_folder import write_volume
from monai_probreg.spatial.volume_io import Volume, read_image

ROTATION_DEG, TRANSLATION_MM, SPACING_MM = 8.0, 6.0, (1.2, 1.0, 1.1)  # the moved scan


def register(moving: Path, out: Path, threads: int) -> dict:
    run_command(
        "register", "--moving", str(moving), "--out", str(out), "--threads", str(threads), "--quiet", "--no-inverse"
    )
    return json.loads((out / "summary.json").read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    template = read_image(mni152_template_path())
    image = template.with_array((template.array - template.array.min()) / np.ptp(template.array))
    empty = Volume(np.zeros(image.shape, np.int16), image.index_to_lps)
    moved, _, _, angles, translation = misalign(
        image, empty, template, np.random.default_rng(args.seed), ROTATION_DEG, TRANSLATION_MM, SPACING_MM
    )
    rows = []
    with tempfile.TemporaryDirectory(prefix="failure_example_") as tmp:
        scan = write_volume(Path(tmp) / "mni_moved.nii.gz", moved, np.int16)
        cases = (
            ("as it is", scan),
            ("header turned by 180 degrees about S", turned_header(scan, 180.0, Path(tmp) / "mni_moved_turned.nii.gz")),
        )
        for n, (name, path) in enumerate(cases):
            summary = register(path, Path(tmp) / f"out{n}", args.threads)
            quality = summary["quality"] or {}
            rows.append((name, plt.imread(Path(tmp) / f"out{n}" / "qc.png")))
            print(
                f"{name}: predicted Dice {quality.get('predicted_dice')}, failure probability "
                f"{quality.get('failure_probability')}, warning: {summary['warning']}",
                flush=True,
            )
    print(f"moved by rotation {np.round(angles, 1).tolist()} deg, translation {np.round(translation, 1).tolist()} mm")
    height = sum(r[1].shape[0] for r in rows)
    fig = plt.figure(figsize=(rows[0][1].shape[1] / 100, height / 100), dpi=100)
    top = 1.0
    for _name, picture in rows:
        share = picture.shape[0] / height
        ax = fig.add_axes([0, top - share, 1, share])
        ax.imshow(picture)
        ax.axis("off")
        top -= share
    args.out_dir.mkdir(parents=True, exist_ok=True)
    out = args.out_dir / "failure_example.png"
    fig.savefig(out, dpi=60)
    plt.close(fig)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
