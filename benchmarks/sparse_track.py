"""The sparse tracker prototype (issue 29, :mod:`ipt.receiver.core.sparse`) on rendered flights, against the dense
pipeline on the same frames.

    python benchmarks/sparse_track.py DIR [DIR ...] [--frames N] [--pairs past,order,...] [--esm-partner]

``DIR`` is a rendering (``bmp/`` frames, ``camera.yaml``, ``arena.yaml``, ``groundtruth.tum``; read only). The
dense :class:`~ipt.receiver.core.pipeline.Pipeline` runs first, in process, for its poses and each frame's
projector phase. Then the sparse tracker runs as a chain, once for each ``--pairs``: it starts from the dense
pose of the first posed frame, and each later frame is fitted with a partner of the other phase, starting from
the chain's poses carried on at constant velocity. ``past`` (round one): each frame k from one of its past
partners k−1…k−3 that has a pose of the chain. ``order``: the partner that shows the same video frame (IPT's
sender shows each one in its + phase, then its −): a + frame waits; a − frame is fitted with a + frame before
it (k−1, k−2, k−3), and when that one has no pose yet both poses are fitted (the partner's held near its
prediction by ``--partner-sigma-px``); the + frame's pose comes out then. ``order2``: the same, partners with
a pose first, and each + frame still waiting then fitted on its own against the − frame's new pose.
``oracle``: the dense pipeline's chosen partner instead of the rule. ``still``: ``order2``, but a + frame
first tries its past partner and takes that fit at once if its residual is as small as the same-content pairs'.
``auto``: ``order2``, but a + frame is fitted at once with its past partner while the floor's content holds still
(judged on each − frame against the − frame of the video frame before, :func:`_content_still`).
When no partner gives a fit that its checks accept, the chain takes the dense pose (a re-seed, counted; a
waiting frame three frames later); frames without one stay unposed. Prints JSON per flight and chain: the
sparse yield, re-seeds, processor time per frame (``time.thread_time`` of everything the fits do: selection,
sampling through the lens, the fit; frames preloaded as lightness, not timed, the lightness's own cost given
apart), the frames each pose waited for and that wait in ms (p50, p99), the errors against the ground truth of
the sparse poses and of the dense poses of the same frames, and the dense pipeline's own processor time per
frame and per stage in the same run. ``joint_guess_error``: how far the joint fits' predicted starts were from the
ground truth (:mod:`sparse_report`). Environment knobs of the joint fits (``SPARSE_JOINT_*``) are read below.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.base import ConfigError
from ipt.config.camera_info import load_camera_info
from ipt.config.models import load_arena_config
from ipt.receiver.core import sparsechain
from ipt.receiver.core.demodulator import luminance
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.sparse import SparseCamera, SparseResult, SparseSettings
from ipt.receiver.core.sparsechain import (
    Chain,
    Pairing,
    chain_settings,
    content_still,
    fitter,
    order_pairing,
    pair_frame,
    past_pairing,
    seed,
    take,
)
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.tum import read_tum

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sparse_report import chain_report
from suite import one_core, receiver_config

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

#: Frames between the two poses whose motion a same-content chain's prediction carries on.
BASELINE = int(os.environ.get("SPARSE_BASELINE", "1"))
#: ... and for the two predicted poses of a joint fit (0: the same).
JOINT_BASELINE = int(os.environ.get("SPARSE_JOINT_BASELINE", "0"))
#: Gauss-Newton iterations of a pair fit whose two poses are both only predicted.
JOINT_ITERATIONS = int(os.environ.get("SPARSE_JOINT_ITERATIONS", "12"))
#: ... of which this many first read wider, smoothed profiles (SparseSettings.coarse_iterations).
JOINT_COARSE = int(os.environ.get("SPARSE_JOINT_COARSE", "1"))
#: ... whose profiles reach this far (pixels at 640 wide) and are smoothed this much (σ, pixels at 640 wide).
JOINT_RADIUS = int(os.environ.get("SPARSE_JOINT_RADIUS", str(SparseSettings.radius_px)))
JOINT_SMOOTH = float(os.environ.get("SPARSE_JOINT_SMOOTH", str(SparseSettings.coarse_smooth_px)))
#: ... which read every second sample while their last step moved one by more than this (pixels at 640; 0: all).
JOINT_HALF_UNTIL_PX = float(os.environ.get("SPARSE_JOINT_HALF_UNTIL_PX", "0"))
#: ... and the largest last step (pixels) with which such a fit is taken as settled.
JOINT_SETTLED_PX = float(os.environ.get("SPARSE_JOINT_SETTLED_PX", "0.6"))


def load_frames(folder: Path, frames: int | None, method: str) -> tuple[list[npt.NDArray[Any]], list[U8], float]:
    """The rendering's frames as the camera delivers them, their lightness (raw: not undistorted) and its
    processor time per frame."""
    names = sorted((folder / "bmp").glob("*.bmp"))[:frames]
    if not names:
        raise SystemExit(f"sparse_track: {folder / 'bmp'}: no BMP frames")
    raw, lum, spent = [], [], 0.0
    for name in names:
        image = cv2.imread(str(name), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SystemExit(f"sparse_track: {name}: not a readable image")
        frame = image if image.ndim == 2 else np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        raw.append(frame)
        t0 = time.thread_time()
        lum.append(luminance(frame, method))
        spent += time.thread_time() - t0
    return raw, lum, spent / len(names)


def run_dense(
    pipeline: Pipeline, raw: list[npt.NDArray[Any]], times_us: list[int]
) -> tuple[dict[int, FrameResult], dict[int, int], float]:
    """The dense pipeline's results by frame, each frame's projector phase as it learnt it, and its processor
    time per frame."""
    results: list[FrameResult] = []
    phase: dict[int, int] = {}
    spent = 0.0
    for k, frame in enumerate(raw):
        t0 = time.thread_time()
        results += pipeline.process(k, frame, times_us[k])
        spent += time.thread_time() - t0
        for f in pipeline.history:
            if f.phase is not None:
                phase[f.index] = f.phase
    results += pipeline.flush()
    return {r.index: r for r in results}, phase, spent / len(raw)


def oracle_pairing(dense: dict[int, FrameResult], phase: dict[int, int]) -> Pairing:
    """The dense pipeline's winning partner of each frame (an oracle: it looked at frames ahead)."""
    chosen = {
        k: r.partner for k, r in dense.items() if r.partner is not None and phase.get(r.partner) == -phase.get(k, 0)
    }
    claims: dict[int, list[int]] = {}
    for k, j in sorted(chosen.items()):
        if j > k:
            claims.setdefault(j, []).append(k)

    def partners(k: int) -> list[int]:
        own = [chosen[k]] if k in chosen and chosen[k] < k else []
        return own + [j for j in claims.get(k, []) if j not in own]

    return Pairing(lambda k: k in chosen and chosen[k] > k, partners, BASELINE, JOINT_BASELINE)


def run_sparse(
    lum: list[U8],
    dense: dict[int, FrameResult],
    phase: dict[int, int],
    times_us: list[int],
    camera: SparseCamera,
    edges: MapEdges,
    settings: SparseSettings,
    pairing: Pairing,
    partner_sigma_px: float,
) -> tuple[Chain, float, int]:
    """The chain over the frames; its processor time (sparse work only) and the frames it worked on. A frame
    that waits for a later partner (``pairing``) gets its pose with that partner's; if none has given it one
    by three frames later, the chain takes its dense pose then (a re-seed)."""
    known, joint = chain_settings(
        camera.size[0],
        partner_sigma_px=partner_sigma_px,
        base=settings,
        joint_iterations=JOINT_ITERATIONS,
        joint_coarse=JOINT_COARSE,
        joint_settled_px=JOINT_SETTLED_PX,
        joint_radius_px=JOINT_RADIUS,
        joint_smooth_px=JOINT_SMOOTH,
        joint_half_until_px=JOINT_HALF_UNTIL_PX,
    )
    fit = fitter(camera, edges, known, joint)

    chain = Chain()
    spent, worked = 0.0, 0
    first = next((k for k in range(len(lum)) if k in dense and dense[k].pose is not None), None)
    if first is not None:  # the kernels compiled (or loaded from numba's cache) before the clock starts
        pose = dense[first].pose
        assert pose is not None
        rt = rt_of(pose.position_m, pose.r_arena_cam)
        fit(lum[first], lum[first], rt, rt, 0.0, False)
    pending: list[int] = []
    past = replace(past_pairing(phase), baseline=BASELINE)
    frames, times = dict(enumerate(lum)), dict(enumerate(times_us))
    for k in range(len(lum)):
        out: dict[int, SparseResult] = {}
        started = bool(chain.rt)
        if started:
            worked += 1
            t0 = time.thread_time()
            if not pairing.waits(k):
                out = pair_frame(chain, k, frames, phase, times, fit, pairing)
                if k in out:
                    chain.same_rms.append(out[k].rms_px)
            elif pairing.past_first:
                out = _past_if_still(
                    chain, k, lum, phase, times_us, fit, replace(past_pairing(phase), baseline=BASELINE)
                )
            elif pairing.auto and chain.still:
                out = pair_frame(chain, k, frames, phase, times, fit, past)
            spent += time.thread_time() - t0
        for j, result in out.items():
            take(chain, j, result, k)
        if pairing.auto and k in out and not pairing.waits(k):
            t0 = time.thread_time()
            chain.still = bool(content_still(chain, k, frames, phase, camera, edges, STILL_SPREAD))
            spent += time.thread_time() - t0
        if k not in out and started and pairing.waits(k):
            pending.append(k)
        elif k not in out:
            _reseed(chain, k, dense, phase)
        for j in [j for j in pending if j <= k - 3 or k == len(lum) - 1]:
            pending.remove(j)
            if j not in chain.rt:
                _reseed(chain, j, dense, phase)
    return chain, spent, worked


def _past_if_still(
    chain: Chain, k: int, lum: dict[int, U8], phase: dict[int, int], times_us: dict[int, int], fit: Any, past: Pairing
) -> dict[int, SparseResult]:
    """A waiting frame's fit with a past partner (of the video frame before), taken at once if its residual is
    no more than :data:`STILL_RATIO` times the recent same-content pairs' (the content held still)."""
    if not chain.same_rms:
        return {}
    found = pair_frame(chain, k, lum, phase, times_us, fit, past)
    if k in found and found[k].rms_px <= STILL_RATIO * float(np.median(chain.same_rms[-16:])):
        return found
    chain.refused["content_moved"] += 1 if k in found else 0
    return {}


def _reseed(chain: Chain, k: int, dense: dict[int, FrameResult], phase: dict[int, int]) -> None:
    """The dense pose of ``k`` into the chain, if it has one."""
    if k in dense and dense[k].pose is not None and k in phase:
        pose = dense[k].pose
        assert pose is not None
        seed(chain, k, rt_of(pose.position_m, pose.r_arena_cam), phase[k])


#: The chains the benchmark can run: which frames are paired (``--pairs``).
PAIRINGS = ("past", "oracle", "order", "order2", "still", "auto")
#: The spread of two same-phase frames' difference (a video frame apart) up to this many times a pair fit's
#: residual: the content held still (:data:`~ipt.receiver.core.sparsechain.STILL_SPREAD`).
STILL_SPREAD = float(os.environ.get("SPARSE_STILL_SPREAD", str(sparsechain.STILL_SPREAD)))
#: A past pair's residual up to this many times the same-content pairs' (median of the last 16): the content
#: held still, and a first-phase frame's fit with the video frame before is taken at once.
STILL_RATIO = float(os.environ.get("SPARSE_STILL_RATIO", "1.2"))


def _pairing(name: str, dense: dict[int, FrameResult], phase: dict[int, int]) -> Pairing:
    if name == "oracle":
        return oracle_pairing(dense, phase)
    order = order_pairing(phase, 1, tuple(int(b) for b in os.environ.get("SPARSE_ORDER", "1,2,3").split(",")))
    if name == "auto":
        chosen = replace(order, known_first=True, refine=True, auto=True)
    elif name == "still":
        chosen = replace(order, known_first=True, refine=True, past_first=True)
    elif name == "order2":
        chosen = replace(order, known_first=True, refine=True)
    else:
        chosen = order if name == "order" else past_pairing(phase)
    return replace(chosen, baseline=BASELINE, joint_baseline=JOINT_BASELINE)


def flight(
    folder: Path, frames: int | None, settings: SparseSettings, pairings: list[str], partner_sigma_px: float
) -> dict[str, Any]:
    try:
        arena = load_arena_config(folder / "arena.yaml")
    except (ConfigError, OSError) as exc:
        raise SystemExit(f"sparse_track: {folder / 'arena.yaml'}: {exc}") from None
    camera = load_camera_info(folder / "camera.yaml")
    truth = read_tum(folder / "groundtruth.tum")
    cfg = receiver_config("ipt", False)
    raw, lum, lightness_s = load_frames(folder, frames, cfg.demodulation.lightness)
    times_us = [round(float(truth.times_s[k]) * 1e6) for k in range(len(raw))]
    tag_map = grid_tag_map(arena)
    out: dict[str, Any] = {"frames": len(raw), "lightness_ms_per_frame": round(1e3 * lightness_s, 3)}
    with one_core():
        pipeline = Pipeline(
            tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, tag_map.by_id)
        )
        try:
            dense, phase, dense_s = run_dense(pipeline, raw, times_us)
        finally:
            pipeline.close()
        out["dense_yield_pct"] = round(100.0 * sum(1 for r in dense.values() if r.pose is not None) / len(raw), 1)
        out["dense_ms_per_frame"] = round(1e3 * dense_s, 3)
        out["dense_stage_ms_per_frame"] = {s: round(1e3 * v / len(raw), 3) for s, v in pipeline.stage_seconds.items()}
        sparse_camera = SparseCamera.of(camera.camera_matrix, camera.dist_coeffs, (camera.width_px, camera.height_px))
        edges = MapEdges.from_tag_map(tag_map)
        for name in pairings:
            chain, sparse_s, worked = run_sparse(
                lum,
                dense,
                phase,
                times_us,
                sparse_camera,
                edges,
                settings,
                _pairing(name, dense, phase),
                partner_sigma_px,
            )
            out[name] = chain_report(chain, sparse_s, worked, dense, phase, truth, times_us, sparse_camera)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "dirs", nargs="+", type=Path, help="renderings (bmp/, camera.yaml, arena.yaml, groundtruth.tum)"
    )
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--blur-px", type=float, default=SparseSettings.blur_px, help="step blur σ at 640 px wide")
    parser.add_argument(
        "--pairs",
        default="past,order",
        help="chains to run, comma-separated: past (round one: each frame from its nearest past partner), "
        "oracle (the dense pipeline's partner), order (the same video frame's partner by the phase order), "
        "order2 (order, partners with a pose first, then the waiting + frames), still (a + frame's past fit "
        "taken when its residual is small), auto (past partners while the content holds still, else order2)",
    )
    parser.add_argument(
        "--partner-sigma-px", type=float, default=10.0, help="a predicted partner's uncertainty, px at 640 wide"
    )
    parser.add_argument(
        "--esm-partner",
        action="store_true",
        help="the partner's slope averaged with this frame's (SparseSettings.esm_partner)",
    )
    parser.add_argument(
        "--known-sigma-px", type=float, default=SparseSettings.other_sigma_px, help="a fitted partner's, px"
    )
    args = parser.parse_args()
    if args.frames is not None and args.frames < 10:
        print(f"sparse_track: --frames {args.frames}: need at least 10", file=sys.stderr)
        return 2
    for d in args.dirs:
        for need in ("bmp", "camera.yaml", "arena.yaml", "groundtruth.tum"):
            if not (d / need).exists():
                print(f"sparse_track: {d}: no {need}", file=sys.stderr)
                return 2
    pairings = args.pairs.split(",")
    if not pairings or any(p not in PAIRINGS for p in pairings):
        print(f"sparse_track: --pairs {args.pairs}: each must be one of {', '.join(PAIRINGS)}", file=sys.stderr)
        return 2
    if args.partner_sigma_px <= 0:
        print(f"sparse_track: --partner-sigma-px {args.partner_sigma_px}: must be positive", file=sys.stderr)
        return 2
    settings = SparseSettings(
        blur_px=args.blur_px,
        esm_partner=args.esm_partner,
        other_sigma_px=args.known_sigma_px,
        max_partner_px=max(SparseSettings.max_partner_px, 3.0 * args.known_sigma_px),
    )
    out = {
        "load": os.getloadavg()[0],
        "flights": {d.name: flight(d, args.frames, settings, pairings, args.partner_sigma_px) for d in args.dirs},
    }
    out["load_after"] = os.getloadavg()[0]
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
