"""skycap reconstruction."""
