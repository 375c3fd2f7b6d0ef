"""What the ``monai-probreg`` command prints from a registration's summary: the one line of a scan
(:func:`summary_line`), the demo's report (:func:`demo_report`) and a batch's table (:func:`print_batch_table`).
The summaries themselves come from :mod:`monai_probreg.registration`."""

from __future__ import annotations

from collections.abc import Sequence

from monai_probreg.registration.batch import BatchRow

__all__ = ["demo_report", "print_batch_table", "summary_line"]


def summary_line(summary: dict) -> str:
    """The line the command prints for one registration: the times, Dice, folding and the quality estimate."""
    t = summary["timings_s"]
    parts = [f"total {t['total']:.1f} s (" + ", ".join(f"{k} {v:.1f}" for k, v in t.items() if k != "total") + ")"]
    if summary.get("dice"):
        parts.append(f"mean Dice {summary['dice']['mean']:.3f} (affine only {summary['dice']['mean_affine_only']:.3f})")
    parts.append(f"|J|<=0: {summary['jacobian']['num_nonpositive']}")
    if summary.get("quality"):
        parts.append(
            f"predicted Dice {summary['quality']['predicted_dice']:.2f}, "
            f"failure probability {summary['quality']['failure_probability']:.2f}"
        )
    elif summary.get("quality_not_estimated"):  # its label, up to the first colon (summary.json has the whole reason)
        parts.append(f"no quality estimate ({summary['quality_not_estimated'].split(':')[0]})")
    return "; ".join(parts)


def _fmt(value: float | None) -> str:
    return "    -" if value is None else f"{value:5.2f}"


def demo_report(summary: dict) -> str:
    """The lines ``monai-probreg demo`` prints: what was drawn, the errors, the coverage."""
    demo = summary["demo"]
    rotation = ", ".join(f"{a:.1f}" for a in demo["rotation_deg"])
    shift = ", ".join(f"{t:.1f}" for t in demo["shift_mm"])
    lines = [
        (
            f"demo (seed {demo['seed']}): the template turned by ({rotation}) deg, shifted by ({shift}) mm and "
            f"deformed (velocity RMS {demo['settings']['deform_rms_mm']} mm), with a bias field and noise"
        ),
        "displacement error inside the brain, mm     median   95th pct",
    ]
    for key, text in (
        ("before", "before registration"),
        ("affine_only", "after the affine stage"),
        ("after", "after registration"),
    ):
        row = demo[key] or {"median_mm": None, "p95_mm": None}
        lines.append(f"  {text:<40}{_fmt(row['median_mm'])}    {_fmt(row['p95_mm'])}")
    if demo["coverage"] is None:
        lines.append("interval coverage: needs --samples >= 2")
    else:
        tails = "" if demo.get("interval_dof") is None else f" (Student-t, {demo['interval_dof']:g} dof)"
        lines.append(
            f"calibrated {demo['coverage_level']:.0%} interval{tails}: covers {demo['coverage']:.1%} of the error "
            f"components (the truth itself is exact to {demo['truth_inverse_error_mm']:.2f} mm)"
        )
    return "\n".join(lines)


def print_batch_table(rows: Sequence[BatchRow], file=None) -> None:
    """The summary as an aligned table on stdout (or ``file``)."""

    def fmt(value, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    print(
        f"{'scan':<24}{'status':<8}{'Dice':>7}{'affine':>8}{'|J|<=0':>8}{'time (s)':>10}{'pred.':>7}  error / warning",
        file=file,
    )
    for r in rows:
        note = r.error or (f"WARNING: {r.warning}" if r.warning else "")
        print(
            f"{r.scan:<24}{r.status:<8}{fmt(r.mean_dice, '.3f'):>7}{fmt(r.mean_dice_affine_only, '.3f'):>8}"
            f"{fmt(r.num_jacobian_nonpositive, 'd'):>8}{fmt(r.time_s, '.1f'):>10}{fmt(r.predicted_dice, '.2f'):>7}"
            f"  {note}",
            file=file,
        )
