"""skycap: markerless human motion capture from a fleet of autonomous camera drones.

This package is the base layer that every part shares and that imports no other part: errors
(:mod:`skycap.errors`), logging set-up (:mod:`skycap.logsetup`), typed
configuration (:mod:`skycap.config`), frames and rotations (:mod:`skycap.frames`), the BVH reader and
writer (:mod:`skycap.bvh`) and the body skeleton conventions (:mod:`skycap.skeleton`).
"""

__version__ = "0.1.0"
