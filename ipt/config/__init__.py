"""Settings: pydantic models (unknown keys rejected, every field described) and their YAML loaders.

Shipped examples live beside this file: ``arena.yaml`` (the paper's arena).
"""

from ipt.config.camera_info import CameraInfo, CameraInfoError, load_camera_info, save_camera_info
from ipt.config.models import (
    ArenaConfig,
    ConfigError,
    DemodulationConfig,
    DetectorConfig,
    ModulationConfig,
    PipelineConfig,
    PoseConfig,
    ProjectorConfig,
    ScreenConfig,
    TagMapConfig,
    load_arena_config,
    load_yaml_model,
    shipped_config_path,
)

__all__ = [
    "ArenaConfig",
    "CameraInfo",
    "CameraInfoError",
    "ConfigError",
    "DemodulationConfig",
    "DetectorConfig",
    "ModulationConfig",
    "PipelineConfig",
    "PoseConfig",
    "ProjectorConfig",
    "ScreenConfig",
    "TagMapConfig",
    "load_arena_config",
    "load_camera_info",
    "load_yaml_model",
    "save_camera_info",
    "shipped_config_path",
]
