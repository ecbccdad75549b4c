import sys

from simgap.cli import main

sys.exit(main())
