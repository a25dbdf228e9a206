"""Settings of the simulated arena: the drone's camera, its timing and noise, and the flight."""

from __future__ import annotations

from pydantic import Field, model_validator

from ipt.config.models import StrictModel


class SimCameraConfig(StrictModel):
    """The drone's downward global-shutter camera."""

    width_px: int = Field(640, ge=32, le=8192, description="Image width in pixels.")
    height_px: int = Field(360, ge=32, le=8192, description="Image height in pixels.")
    fx_px: float = Field(460.0, gt=0, description="Focal length along x, pixels.")
    fy_px: float = Field(460.0, gt=0, description="Focal length along y, pixels.")
    cx_px: float = Field(319.5, description="Principal point x (OpenCV: pixel centres are integers).")
    cy_px: float = Field(179.5, description="Principal point y.")
    distortion: tuple[float, float, float, float, float] = Field(
        (-0.08, 0.03, 0.0004, -0.0003, 0.0), description="plumb_bob k1 k2 p1 p2 k3."
    )
    fps: float = Field(120.0, gt=0, le=1000, description="Frame rate; frame k is exposed around k / fps.")
    exposure_ms: float = Field(4.0, gt=0, description="Exposure time, centred on the frame time.")
    gain: float = Field(0.85, gt=0, description="Linear signal of full projector white (1 = saturation).")
    ambient: float = Field(0.04, ge=0, description="Room light on the floor, in units of projector white.")
    blur_sigma_px: float = Field(0.6, ge=0, description="Optical blur (Gaussian sigma) in camera pixels.")
    read_noise: float = Field(0.003, ge=0, description="Read noise, fraction of full scale (linear).")
    full_well_e: float = Field(4000.0, gt=0, description="Electrons at saturation (sets the shot noise).")
    supersample: int = Field(2, ge=1, le=4, description="Render at this multiple of the size, then average.")
    time_samples: int = Field(3, ge=1, le=16, description="Instants rendered per exposure (motion blur).")

    @model_validator(mode="after")
    def _check(self) -> SimCameraConfig:
        if self.exposure_ms * 1e-3 > 1.0 / self.fps:
            raise ValueError(f"exposure {self.exposure_ms} ms is longer than a frame at {self.fps} FPS")
        return self


class SimFlightConfig(StrictModel):
    """The paper's flight: a rectangle at about 0.8 m, up to about 1 m/s."""

    size_m: tuple[float, float] = Field((1.0, 1.2), description="Rectangle sides along arena x and y.")
    centre_m: tuple[float, float] = Field((0.0, 0.0), description="Rectangle centre in the arena.")
    altitude_m: float = Field(0.8, gt=0.1, le=10, description="Mean camera height above the floor.")
    altitude_wobble_m: float = Field(0.03, ge=0, description="Amplitude of the slow height wobble.")
    peak_speed_mps: float = Field(1.0, gt=0, le=10, description="Top speed, reached mid-edge.")
    heading_deg: float = Field(0.0, description="Mean heading (yaw of the body x axis from arena x).")
    yaw_wobble_deg: float = Field(8.0, ge=0, le=90, description="Amplitude of the slow yaw wobble.")


class SimConfig(StrictModel):
    """The simulated arena: a camera flying over the projected, modulated floor."""

    camera: SimCameraConfig = Field(default_factory=SimCameraConfig, description="The drone's camera.")
    flight: SimFlightConfig = Field(default_factory=SimFlightConfig, description="The flight path.")
    projector_offset_ms: float = Field(
        1.3, description="Time of the projector's first frame flip after t = 0 (phase against the camera)."
    )
    projector_clock_ppm: float = Field(
        0.0, ge=-1e5, le=1e5, description="Projector clock error in ppm (e.g. -1000 for 59.94 Hz at 60 Hz)."
    )
    seed: int = Field(0, ge=0, description="Seed for the noise and the generated content.")
