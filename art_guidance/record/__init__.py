"""MCAP recording of every solve (rosbag2 layout, ros2msg schemas, cdr), its replay and the
repair of a folder left by a crash (`reindex`)."""
