import sys

from mapmatch.cli import main

sys.exit(main())
