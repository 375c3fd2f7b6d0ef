"""Helpers of the bundle workflow tests: an initialised infer workflow, unwrapping MONAI config errors."""

from __future__ import annotations

from pathlib import Path

from monai.bundle import ConfigWorkflow

from monai_probreg.fitting.stages import config_files

NETWORK_SIZE = [16, 16, 16]


def infer_workflow(config: str, bundle: Path, dataset: Path, output: Path, **override) -> ConfigWorkflow:
    """``configs/<config>`` of ``bundle`` (an overlay on top of its base, as documented) as an initialised infer
    workflow on ``dataset`` writing to ``output``."""
    settings = {
        "bundle_root": str(bundle),
        "dataset_dir": str(dataset),
        "output_dir": str(output),
        "network_size": NETWORK_SIZE,
        "num_workers": 0,
        **override,
    }
    wf = ConfigWorkflow(
        config_file=[str(f) for f in config_files(bundle, [config])],
        workflow_type="infer",
        logging_file=False,
        **settings,
    )
    wf.initialize()
    return wf


def root_cause(exc: BaseException) -> BaseException:
    """MONAI wraps errors of config expressions in RuntimeError('Failed to evaluate ...'); unwrap them."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return exc
