"""``python -m mapmatch``: the ``mapmatch`` command."""

import sys

try:
    from mapmatch.cli import main
except KeyboardInterrupt:  # Ctrl-C while starting up
    print("mapmatch: interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
