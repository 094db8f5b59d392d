"""skycap: markerless human motion capture from a fleet of autonomous camera drones.

This package holds what every part shares: the command-line tool (:mod:`skycap.cli`), typed
configuration (:mod:`skycap.config`), frames and rotations (:mod:`skycap.frames`), the BVH reader and
writer (:mod:`skycap.bvh`) and the body skeleton conventions (:mod:`skycap.skeleton`).
"""

__version__ = "0.1.0"
