"""The simulator's scene: the person, the cameras and the simulated detectors.

* :mod:`simulator.scene.person` -- :class:`PersonSim`: real CMU motion (committed clips in
  ``simulator/data/motions``) walked along waypoints with motions at stops; ``state_at(t_s)``.
* :mod:`simulator.scene.body` -- the rendered body: 16 ellipsoids from the 17 COCO joints.
* :mod:`simulator.scene.camera` -- pinhole camera, gimbal/fixed mount, exact projections, body box,
  self-occlusion.
* :mod:`simulator.scene.render` -- :class:`Renderer`: textured ground, sky, shaded body, shadow; JPEG.
* :mod:`simulator.scene.sim_detector` -- simulated keypoint and box detectors (noisy ground truth).
* :mod:`simulator.scene.camera_node` -- :class:`CameraNode`: one drone's camera loop (truth in,
  messages out), network-free; :mod:`simulator.scene.node` wires it to Zenoh (``skycap sim-camera``).
* :mod:`simulator.scene.config` -- :class:`SceneConfig` (person, camera, sim_detector).
"""
