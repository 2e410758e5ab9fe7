"""``python -m companion.cli``: the ``companion`` command (the demo, the soak and the tests run
the service this way)."""

import sys

from companion.cli import main

sys.exit(main())
