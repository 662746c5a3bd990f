"""MCAP recording of every solve (rosbag2 layout, ros2msg schemas, cdr) and its replay."""
