import sys

from platformd.cli import main

sys.exit(main())
