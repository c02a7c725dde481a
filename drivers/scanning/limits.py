"""Default bounds of the scan readers' resource options.

Here rather than beside the readers so that the service's settings can take them as defaults
without importing a reader's dependencies (Open3D takes seconds to import).
"""

from __future__ import annotations

#: Largest depth image read, pixels: 4096 x 4096. Depth cameras stay well below it (RealSense
#: D4xx 1280 x 720, Azure Kinect 1024 x 1024, Zivid 2+ 2448 x 2048); one frame of that size
#: takes about 0.9 GB and 6 s to read (measured at 64 MP: 3.4 GB, 21 s).
DEFAULT_MAX_FRAME_PIXELS = 4096 * 4096
#: Largest number of pixels read over all frames of a scan: eight frames of the largest size,
#: 145 at 1280 x 720 or 436 at 640 x 480. TSDF fusion integrates about 6 MP/s here (30 frames of
#: 640 x 480 in 1.5 s), so about 22 s.
DEFAULT_MAX_PIXELS = 8 * 4096 * 4096
