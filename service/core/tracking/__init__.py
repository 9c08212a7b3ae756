"""Tracking from a known pose: the shape tracker (:class:`~service.core.tracking.localizer.
ShapeLocalizer`), the motion model (odometry or the robot's own velocity) and the odometry
checked against the scans."""
