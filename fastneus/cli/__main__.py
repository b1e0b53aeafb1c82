"""``python -m fastneus.cli``: the same as the ``fastneus`` command."""
import sys

from fastneus.cli import main

sys.exit(main())
