"""``python -m monai_probreg.cli``: the same as the ``monai-probreg`` command."""

from monai_probreg.cli.main import run

run()
