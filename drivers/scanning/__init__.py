"""Scan readers: point clouds, E57, RGB-D frames and RealSense bags, chosen by file suffix.

Entry point: :func:`drivers.scanning.pointcloud.read_scan` (the same as
:func:`drivers.scanning.base.read_scan`); the registry is in :mod:`drivers.scanning.base`.
Nothing is imported here, so that importing the package loads no reader's dependencies.
"""
