"""skycap onboard."""
