"""``python -m monai_probreg.fitting``: refit the calibration and the quality model, write both sidecars."""

from monai_probreg.fitting.command import main

raise SystemExit(main())
