"""The ROS 2 wire as rmw_zenoh (ROS 2 Jazzy) puts it on Zenoh: pure functions, no zenoh.

* :mod:`schemas.ros2.types`: the message types of the target distribution (Jazzy) with their
  DDS names and RIHS01 hashes, from ``rosbags``' type store;
* :mod:`schemas.ros2.cdr`: CDR encode / decode of LaserScan, TFMessage, Odometry,
  PoseWithCovarianceStamped and OccupancyGrid as planar values, every decode checked;
* :mod:`schemas.ros2.graph`: ROS names, data key expressions, liveliness tokens, QoS strings
  and GIDs as rmw_zenoh writes them;
* :mod:`schemas.ros2.attachment`: the per-sample attachment (sequence number, timestamp, GID).

What is followed, and from which rmw_zenoh version: docs/ros2.md.
"""
