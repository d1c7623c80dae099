"""`python -m laser_calib.cli`: the laser-calib command line."""

import sys

from laser_calib.cli.main import main

sys.exit(main())
