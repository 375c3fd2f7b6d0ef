"""``python -m monai_probreg.cli``: the same as the ``monai-probreg`` command."""

import sys

from monai_probreg.cli.main import main

sys.exit(main())
