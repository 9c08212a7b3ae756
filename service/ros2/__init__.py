"""The ROS 2 front: ROS 2 robots over rmw_zenoh served by shapeloc (docs/ros2.md).

:mod:`service.ros2.tf` (planar tf buffer), :mod:`service.ros2.robot` (one namespace's state
and translation, no I/O), :mod:`service.ros2.front` (the Zenoh side), ``python -m
service.ros2`` (the front as its own process).
"""
