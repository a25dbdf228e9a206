"""``ipt sim``: render a simulated flight to a folder (frames.mkv, camera.yaml, groundtruth.tum)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TextIO

import numpy as np
import yaml

from ipt.calib.floor import HEADER
from ipt.config.camera_info import save_camera_info
from ipt.config.models import ArenaConfig
from ipt.errors import IptError
from ipt.fileio import output_group, write_text_atomic
from ipt.geometry import quat_wxyz_from_matrix
from ipt.sender.content import ContentSource
from ipt.sim.arena import SimulatedArena, survey_points
from ipt.sim.config import SimConfig
from ipt.sim.render import camera_info_of
from ipt.tagmap import TagMap
from ipt.tum import Trajectory, write_tum
from ipt.videoio import FfvWriter

VIDEO_NAME = "frames.mkv"
CAMERA_NAME = "camera.yaml"
TRUTH_NAME = "groundtruth.tum"
ARENA_NAME = "arena.yaml"
SETTINGS_NAME = "sim.json"
SURVEY_NAME = "survey.csv"


class SimError(IptError):
    """The simulation cannot be run as asked."""


@output_group()  # every file this writes is put in place at its end, all together, or removed on any failure
def simulate_to_folder(
    arena: ArenaConfig,
    sim: SimConfig,
    scene: ContentSource,
    out_dir: Path,
    seconds: float,
    tag_map: TagMap | None = None,
    progress: TextIO | None = sys.stderr,
) -> int:
    """Render ``seconds`` of flight into ``out_dir``; returns the number of frames.

    The five files (frames.mkv, camera.yaml, groundtruth.tum, sim.json, arena.yaml; and survey.csv for a
    keystoned flight) are written beside
    their names and put in place together when the run ends (:func:`ipt.fileio.output_group`): a failure
    in any of them (a full disk, an error, a stop signal) leaves none of them and no temporary file, so an
    interrupted run never leaves a folder that looks finished. A previous run's files are removed first.
    """
    if seconds <= 0:
        raise SimError(f"--seconds must be positive, got {seconds}")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimError(f"{out_dir}: cannot create the output folder ({exc.strerror})") from None
    for name in (VIDEO_NAME, CAMERA_NAME, TRUTH_NAME, ARENA_NAME, SETTINGS_NAME, SURVEY_NAME):
        # A previous run's files would look like this run's result if we stopped half way.
        try:
            (out_dir / name).unlink(missing_ok=True)
        except OSError as exc:
            raise SimError(f"{out_dir / name}: cannot remove the previous run's file ({exc.strerror})") from None
    cam = sim.camera
    count = max(1, round(seconds * cam.fps))
    world = SimulatedArena(arena, sim, scene, tag_map)
    times, positions, quats = [], [], []
    start = last = time.monotonic()
    with FfvWriter(out_dir / VIDEO_NAME, cam.width_px, cam.height_px, cam.fps, grey=cam.mono) as writer:
        for f in world.frames(count):
            writer.write(f.image_rgb)
            times.append(f.time_s)
            positions.append(f.truth.position_m)
            quats.append(quat_wxyz_from_matrix(f.truth.r_arena_cam))
            now = time.monotonic()
            if progress is not None and (now - last >= 1.0 or f.index + 1 == count):
                last = now
                rate = (f.index + 1) / (now - start)
                eta = (count - f.index - 1) / rate if rate > 0 else 0.0
                progress.write(f"sim: frame {f.index + 1}/{count} ({rate:.0f} frames/s, {eta:.0f} s left)\n")
                progress.flush()
    save_camera_info(camera_info_of(cam), out_dir / CAMERA_NAME)
    write_tum(out_dir / TRUTH_NAME, Trajectory.from_arrays(np.array(times), np.array(positions), np.array(quats)))
    write_text_atomic(out_dir / SETTINGS_NAME, sim.model_dump_json(indent=1) + "\n")
    flown = "# The arena this flight was rendered with (the --config arena with the flight's changes).\n"
    survey = survey_points(world.arena, sim)
    if survey:
        flown += (
            "# The projector's image is keystoned on the floor (sim.json: keystone): this is the layout the\n"
            f"# receiver is told, not where the pixels land. {SURVEY_NAME} is a survey of it for ipt calibrate arena.\n"
        )
        rows = "".join(f"{u:g},{v:g},{x:.6f},{y:.6f}\n" for u, v, x, y in survey)
        write_text_atomic(out_dir / SURVEY_NAME, ",".join(HEADER) + "\n" + rows)
    write_text_atomic(
        out_dir / ARENA_NAME, flown + yaml.safe_dump(world.arena.model_dump(mode="json"), sort_keys=False)
    )
    return count
