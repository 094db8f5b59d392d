"""Applications: the command-line registry (``skycap``), the demo launcher and its process supervisor."""
