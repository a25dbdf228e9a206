"""A rendered flight's frames and a receiver pipeline for its folder (arena.yaml, camera.yaml, frames.mkv, as
``ipt sim`` writes them), as the pipeline tests make them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ipt.config.camera_info import CameraInfo, load_camera_info
from ipt.config.models import PipelineConfig, load_arena_config
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.videoio import open_frames


def flight_frames(folder: Path) -> list[Any]:
    """Every frame of ``folder``'s recording, decoded (RGB)."""
    with open_frames(folder / "frames.mkv") as src:
        return list(src)


def flight_pipeline(folder: Path, cfg: PipelineConfig, camera: CameraInfo | None = None) -> Pipeline:
    """A pipeline with ``cfg`` for ``folder``'s arena (its tag map and projector rate) and camera (or ``camera``);
    the caller closes it (its AprilTag helper process)."""
    arena = load_arena_config(folder / "arena.yaml")
    tag_map = grid_tag_map(arena)
    camera = camera if camera is not None else load_camera_info(folder / "camera.yaml")
    return Pipeline(tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, tag_map.by_id))
