"""skycap shared_msgs."""
