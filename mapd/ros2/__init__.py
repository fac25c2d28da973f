"""ROS 2 without a ROS install: ``nav_msgs`` CDR and rmw_zenoh's key expressions (:mod:`~mapd.ros2.cdr`),
and zenoh config files read as untrusted input (:mod:`~mapd.ros2.zenoh_config`)."""
