"""``python -m drivers.robot.fake_ur --host 127.0.0.2``."""

import sys

from drivers.robot.fake_ur import main

sys.exit(main())
