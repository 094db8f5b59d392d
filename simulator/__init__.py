"""skycap simulator."""
