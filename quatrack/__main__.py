import sys

from quatrack.cli import main

sys.exit(main())
