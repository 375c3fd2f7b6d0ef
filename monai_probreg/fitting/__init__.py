"""Fitting the sidecars the weights ship with: the posterior calibration and the quality model.

The cases each fit registers and the fits themselves are product, not benchmark: ``python -m monai_probreg.fitting``
(``command``) refits both for the bundle's network and refinement and writes ``<weights stem>.calibration.json`` and
``<weights stem>.quality.json``; ``benchmarks/uncertainty_calibration.py`` and ``benchmarks/failure_detection.py``
import the same functions and only measure (held-out folds, validation subjects, tables).

- the calibration: ``population_probe`` (known deformations of the atlas), ``subject_probe`` (synthetic subjects
  through the command's path), ``calibration_probes`` (both registered, and the coverage-matching fit);
- the quality model: ``failure_set`` (perturbations of a moving scan), ``self_cases`` (a training subject onto itself
  and onto a near copy: almost nothing to register), ``quality_cases`` (the bundle path's cases and the log that
  resumes them), ``command_cases`` (the whole command's), ``quality_fit`` (a split's records and the fit);
- ``stages``: what the bundle says, the two fits, each resumable, and the sidecars; ``command``: the entry point.
"""
