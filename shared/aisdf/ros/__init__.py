"""ROS sources: rosbag recordings (ROS 1, rosbag2 sqlite3 and MCAP) and live ROS 2 robots over
rmw_zenoh, read and (de)serialised with the ``rosbags`` library (no ROS installation)."""
