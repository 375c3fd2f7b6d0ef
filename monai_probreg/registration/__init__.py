"""Registration of raw scans as a library: the product's path from one scan's file to its output folder, which the
``monai-probreg`` command (:mod:`monai_probreg.cli`), the sidecars' fits (:mod:`monai_probreg.fitting`) and the
benchmarks call alike. In the order a scan goes through it:

- :mod:`.model`: the network, its calibration and quality model, from the bundle (loaded once);
- :mod:`.options`: what a registration is asked to do (:class:`~.options.RegistrationOptions`);
- :mod:`.inputs`: the fixed image prepared once (:func:`~.inputs.prepare_fixed`) and the moving scan read;
- :mod:`.affine_stage`: the affine pre-alignment, then the moving scan on the model grid;
- :mod:`.network`: the network's registration, its test-time refinement and the maps;
- :mod:`.quality_estimate`: the label-free quality estimate;
- :mod:`.compose`: affine + deformable composed, the original scan and labels resampled once, Dice;
- :mod:`.output_files`, :mod:`.output_folder`, :mod:`.qc`, :mod:`.summary`: what each file is (``README.txt``),
  the files written all or nothing, the QC figure, ``summary.json``;
- :mod:`.scan`: :func:`~.scan.register_scan`, the stages above in order, timed; :mod:`.batch`: many scans, one bad
  scan never stopping the others; :mod:`.demo`: a synthetic subject with a known answer, registered and scored.

Nothing here is imported at ``import monai_probreg``.
"""
