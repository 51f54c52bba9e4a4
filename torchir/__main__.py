"""``python -m torchir ...`` is the ``torchir`` command."""
import sys

from .cli import main

sys.exit(main())
