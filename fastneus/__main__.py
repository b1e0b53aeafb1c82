"""``python -m fastneus``: the same as the ``fastneus`` command."""
import sys

from fastneus.cli import main

sys.exit(main())
