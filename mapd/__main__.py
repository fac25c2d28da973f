import sys

from mapd.cli import main

sys.exit(main())
