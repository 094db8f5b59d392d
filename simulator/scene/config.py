"""Typed configuration of the simulator's scene: the person, the cameras and the simulated detectors.

Loaded like every skycap config (TOML + ``--set``)::

    cfg = load_config(SceneConfig, path="scene.toml", overrides=["camera.width_px=960", "person.loop=false"])

Defaults: the person walks a 3 m diamond around the origin at the clip's own speed (1.35 m/s),
standing 2 s at the first corner, jumping at the second and punching at the third, so a fixed orbit
around the origin keeps them in view; the camera is 640x360 at 10 Hz with a 70 deg horizontal field of
view on a pitch gimbal (see ``bench/bench_render.py`` for what that costs).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from skycap.config import ConfigError


@dataclass
class StopConfig:
    """What the person does on arriving at waypoint ``waypoint`` (index into ``waypoints_ne_m``)."""

    waypoint: int = 0
    #: clip played there: a built-in motion ("stand", "jump", "punch", "pickup") or a clip in motions_dir
    motion: str = "stand"
    #: seconds spent there; 0 = the clip's own length (a "stand" clip then lasts 2 s)
    duration_s: float = 0.0


def _default_waypoints() -> list[list[float]]:
    return [[1.5, 0.0], [0.0, 1.5], [-1.5, 0.0], [0.0, -1.5]]


def _default_stops() -> list[StopConfig]:
    return [StopConfig(0, "stand", 2.0), StopConfig(1, "jump"), StopConfig(2, "punch"), StopConfig(3, "pickup")]


@dataclass
class PersonConfig:
    """The simulated person: a path of waypoints walked with a real walk cycle, and motions at stops."""

    #: the path [[north_m, east_m], ...]; the person starts at the first waypoint
    waypoints_ne_m: list[list[float]] = field(default_factory=_default_waypoints)
    stops: list[StopConfig] = field(default_factory=_default_stops)
    #: after the last waypoint, walk back to the first and start over (else stand at the last one)
    loop: bool = True
    #: walking clip (a "loop" clip) and idle clip (played while standing)
    walk_motion: str = "walk"
    #: walk faster or slower than the recorded clip: the clip's cadence and the path speed scale together
    #: (stride length kept, so the feet do not slide); 1 = as recorded (1.35 m/s for the built-in walk)
    walk_speed_scale: float = 1.0
    #: cross-fade between walking and a stop's motion, seconds
    blend_s: float = 0.4
    #: time over which the heading turns to a new path direction at a waypoint, seconds
    turn_s: float = 0.6
    #: extra folder of clips (``<name>.npz`` written like simulator/data/make_clips.py); "" = built-in only
    motions_dir: str = ""
    #: appearance (BGR 0..255) of the rendered body
    shirt_bgr: list[int] = field(default_factory=lambda: [60, 60, 200])
    trousers_bgr: list[int] = field(default_factory=lambda: [110, 70, 40])
    skin_bgr: list[int] = field(default_factory=lambda: [120, 150, 200])
    shoes_bgr: list[int] = field(default_factory=lambda: [40, 40, 40])
    hair_bgr: list[int] = field(default_factory=lambda: [30, 45, 70])
    #: the Anny body (``camera.person_model = "anny"``): the seed picks the body shape (one of the baked
    #: Anny phenotypes) and the outfit's colours; one seed per flight, the same for every camera
    body_seed: int = 0
    #: the baked Anny shape to use (0..11); -1 = chosen by ``body_seed``
    body_shape: int = -1

    def validate(self) -> "PersonConfig":
        if len(self.waypoints_ne_m) < 1:
            raise ConfigError("person.waypoints_ne_m is empty; give at least one [north_m, east_m]")
        for p in self.waypoints_ne_m:
            if len(p) != 2:
                raise ConfigError(f"person.waypoints_ne_m entry {p} must be [north_m, east_m]")
        for s in self.stops:
            if not 0 <= s.waypoint < len(self.waypoints_ne_m):
                raise ConfigError(
                    f"person.stops waypoint={s.waypoint} is not an index of the {len(self.waypoints_ne_m)} waypoints"
                )
            if s.duration_s < 0:
                raise ConfigError(f"person.stops duration_s={s.duration_s} must be >= 0 (0 = the clip's length)")
        if not 0.3 <= self.walk_speed_scale <= 2.0:
            raise ConfigError(f"person.walk_speed_scale={self.walk_speed_scale} must be in 0.3..2 (a walk, not a run)")
        if self.blend_s < 0 or self.turn_s < 0:
            raise ConfigError("person.blend_s and person.turn_s must be >= 0")
        for name in ("shirt_bgr", "trousers_bgr", "skin_bgr", "shoes_bgr", "hair_bgr"):
            c = getattr(self, name)
            if len(c) != 3 or not all(0 <= v <= 255 for v in c):
                raise ConfigError(f"person.{name}={c} must be three values 0..255 (blue, green, red)")
        return self


#: (camera.blur_sigma_px, camera.noise_std) that ``-1`` stands for, per person model
CAMERA_EFFECT_DEFAULTS: dict[str, tuple[float, float]] = {"ellipsoids": (0.0, 0.0), "anny": (0.6, 2.0)}


@dataclass
class CameraConfig:
    """A pinhole camera (no distortion) on a pitch gimbal or a fixed mount, rendered by the simulator."""

    camera_id: str = "main"
    width_px: int = 640
    height_px: int = 360
    #: horizontal field of view; fx = fy = (width/2) / tan(hfov/2), principal point at the image centre
    hfov_deg: float = 70.0
    #: "gimbal": roll and pitch stabilised, camera pitch = the vehicle truth's gimbal pitch (or
    #: ``pitch_deg`` when the truth has none); "fixed": rigidly mounted at ``pitch_deg`` to the body
    mount: str = "gimbal"
    #: camera pitch relative to the horizon (gimbal) or to the body (fixed); negative = down
    pitch_deg: float = -20.0
    #: gimbal mount: follow the gimbal pitch in the vehicle truth (``VehicleTruth.gimbal_pitch_rad``)
    #: rather than ``pitch_deg``
    pitch_from_truth: bool = True
    #: camera position in the body FRD frame (metres)
    lever_arm_body_m: list[float] = field(default_factory=lambda: [0.1, 0.0, 0.0])
    rate_hz: float = 10.0
    jpeg_quality: int = 85
    #: CameraInfo is re-sent at this period (and on every change)
    info_period_s: float = 1.0
    #: sun direction (towards the sun) as azimuth from north and elevation above the horizon
    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 50.0
    #: how the person is drawn: "ellipsoids" (17 shaded ellipsoids, fast) or "anny" (a posed Anny body
    #: mesh with clothing colours, for the real keypoint models; see simulator/scene/anny_body.py)
    person_model: str = "ellipsoids"
    #: optics and sensor: Gaussian blur (sigma, px; 0 = none) and additive sensor noise (std, 0..255 levels;
    #: 0 = none), applied to the whole image; the noise is reproducible from ``noise_seed``.
    #: -1 = the person model's default: none with "ellipsoids" (as before), 0.6 px and 2 levels with "anny"
    blur_sigma_px: float = -1.0
    noise_std: float = -1.0
    noise_seed: int = 0

    def camera_effects(self) -> tuple[float, float]:
        """(blur sigma px, noise std levels) in effect, the ``-1`` defaults resolved."""
        blur, noise = CAMERA_EFFECT_DEFAULTS.get(self.person_model, (0.0, 0.0))
        return (blur if self.blur_sigma_px < 0 else self.blur_sigma_px, noise if self.noise_std < 0 else self.noise_std)

    def validate(self) -> "CameraConfig":
        if not (16 <= self.width_px <= 8192 and 16 <= self.height_px <= 8192):
            raise ConfigError(f"camera size {self.width_px}x{self.height_px} must be within 16..8192 px")
        if not 5.0 <= self.hfov_deg <= 150.0:
            raise ConfigError(f"camera.hfov_deg={self.hfov_deg} must be in 5..150 (pinhole model)")
        if self.mount not in ("gimbal", "fixed"):
            raise ConfigError(f"camera.mount={self.mount!r}; use 'gimbal' or 'fixed'")
        if self.rate_hz <= 0:
            raise ConfigError(f"camera.rate_hz={self.rate_hz} must be > 0")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"camera.jpeg_quality={self.jpeg_quality} must be 1..100")
        if len(self.lever_arm_body_m) != 3:
            raise ConfigError("camera.lever_arm_body_m must be [forward_m, right_m, down_m]")
        if self.person_model not in ("ellipsoids", "anny"):
            raise ConfigError(f"camera.person_model={self.person_model!r}; use 'ellipsoids' or 'anny'")
        if not (self.blur_sigma_px == -1.0 or 0.0 <= self.blur_sigma_px <= 10.0):
            raise ConfigError(f"camera.blur_sigma_px={self.blur_sigma_px} must be in 0..10 px (or -1: the default)")
        if not (self.noise_std == -1.0 or 0.0 <= self.noise_std <= 50.0):
            raise ConfigError(f"camera.noise_std={self.noise_std} must be in 0..50 levels (or -1: the default)")
        return self


@dataclass
class SimDetectorConfig:
    """The simulated 2D keypoint detector and person-box detector: ground truth made realistically wrong.

    Keypoint noise std per joint = sqrt(noise_px^2 + (noise_frac_of_height * box_height_px)^2).
    """

    noise_px: float = 1.5
    noise_frac_of_height: float = 0.015
    #: correlation time of the inlier noise (first-order Gauss-Markov per joint and axis, same std):
    #: a real detector's error drifts rather than jumping every frame; 0 = independent per frame
    noise_correlation_s: float = 0.15
    #: mean and spread of an inlier's confidence before it is scaled down with its actual error
    conf_mean: float = 0.85
    conf_std: float = 0.08
    #: probability that a visible joint is missed (reported with confidence 0)
    miss_prob: float = 0.05
    #: probability that a joint is an outlier: uniform in the person's box grown by ``outlier_box_scale``
    outlier_prob: float = 0.03
    outlier_box_scale: float = 1.5
    outlier_conf_min: float = 0.2
    outlier_conf_max: float = 0.6
    #: joints hidden behind another body part (GtProjection.occluded): noise std and confidence scaled,
    #: and missed with their own probability
    occluded_noise_scale: float = 2.0
    occluded_conf_scale: float = 0.5
    occluded_miss_prob: float = 0.15
    #: probability per frame that the whole body is reported left/right swapped
    swap_prob: float = 0.03
    #: a person whose GT box is smaller than this (height, px) is not detected at all
    min_height_px: float = 12.0
    #: box detector: edge noise std as a fraction of the box height, miss probability per frame,
    #: expected number of false alarms per frame (Poisson) and their score range
    box_noise_frac: float = 0.04
    box_miss_prob: float = 0.03
    box_false_alarm_rate: float = 0.05
    box_false_alarm_score_max: float = 0.5
    seed: int = 0

    def validate(self) -> "SimDetectorConfig":
        for name in ("miss_prob", "outlier_prob", "swap_prob", "box_miss_prob", "occluded_miss_prob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"sim_detector.{name}={v} must be a probability in [0, 1]")
        if self.occluded_noise_scale < 0 or not 0 <= self.occluded_conf_scale <= 1:
            raise ConfigError("sim_detector.occluded_noise_scale must be >= 0 and occluded_conf_scale in [0, 1]")
        if self.noise_px < 0 or self.noise_frac_of_height < 0 or self.box_noise_frac < 0:
            raise ConfigError("sim_detector noise values must be >= 0")
        if self.noise_correlation_s < 0:
            raise ConfigError("sim_detector.noise_correlation_s must be >= 0 (0 = white noise)")
        if self.box_false_alarm_rate < 0:
            raise ConfigError("sim_detector.box_false_alarm_rate must be >= 0")
        return self


@dataclass
class SceneConfig:
    """Top-level config of the simulator's scene (``skycap sim-camera``)."""

    person: PersonConfig = field(default_factory=PersonConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    sim_detector: SimDetectorConfig = field(default_factory=SimDetectorConfig)

    def validate(self) -> "SceneConfig":
        self.person.validate()
        self.camera.validate()
        self.sim_detector.validate()
        return self
