"""Recording readers (ROS1 bag, ROS2 bag, MCAP, CARMEN log) behind one Recording interface, and format
detection."""
