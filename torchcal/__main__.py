"""``python -m torchcal``: the same as the ``torchcal`` command."""
from .cli import main

raise SystemExit(main())
