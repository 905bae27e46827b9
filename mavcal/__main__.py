import sys

from mavcal.cli import main

sys.exit(main())
