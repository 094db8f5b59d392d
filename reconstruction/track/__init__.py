"""Offline refinement of a recorded flight (AirCap step 2): a robust RTS smoother over every drone's person
detections giving the refined person track, refined drone positions and per-frame regions of interest
(``skycap refine FLIGHT_DIR``; see :mod:`reconstruction.track.smoother` and :mod:`reconstruction.track.flight`)."""
