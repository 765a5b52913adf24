"""The sensor on a robot's data bus: ROS 2 messages in MCAP files and a live Foxglove stream."""
