"""skycap groundstation."""
