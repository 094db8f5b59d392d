"""The ground-station app (``skycap gs``): PySide6 widgets over the non-Qt fleet model (:mod:`.model`)."""
