"""``python -m nkf_model`` runs the ``nkf`` command line."""

import sys

from .cli import main

sys.exit(main())
