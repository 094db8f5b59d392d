"""The pose dictionary of the monocular method: data file + the script that learns it (see README.md)."""
