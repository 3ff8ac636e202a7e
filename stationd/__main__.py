import sys

from stationd.cli import main

sys.exit(main())
