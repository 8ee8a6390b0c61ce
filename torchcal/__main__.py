"""``python -m torchcal``: the same as the ``torchcal`` command."""
from torchcal.cli.app import main

raise SystemExit(main())
