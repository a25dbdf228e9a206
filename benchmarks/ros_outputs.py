"""The daemon's ROS 2, MCAP and MAVLink outputs on a replayed flight, checked against the replay, as JSON.

    python benchmarks/ros_outputs.py --video DIR [--realtime]

DIR holds frames.mkv and camera.yaml as ``ipt sim`` writes them (``ipt sim --config ipt/config/arena.yaml
--out DIR --seconds 4``); without ``--video`` a flight of ``--seconds`` (default 4) is simulated first.
The real ``ipt-receiver run --source video:DIR/frames.mkv --ros2 --record OUT.mcap --mavlink udpout:...``
subprocess runs once while this script listens on 127.0.0.1: a plain DDS reader (the ROS 2 types, best
effort) on ``rt/ipt/pose``, pymavlink on the MAVLink port, a socket for the UDP pose packets. DDS is
confined to loopback (:mod:`ipt.receiver.outputs.ros.ddsconfig`, a domain of its own). Then ``ipt-receiver replay``
runs on the same recording, and the script reports:

- ``record``: the poses in the MCAP against the replay's TUM file (count, time stamps, largest position
  difference; the TUM file has 1 µm resolution);
- ``ros2``: the poses the DDS reader received out of those in the MCAP;
- ``mavlink``: ODOMETRY per second of capture time (the most in any 1 s window, from ``time_usec``), the
  smallest interval, and how many carried a finite velocity.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

import numpy as np

from ipt.receiver.outputs.ros.ddsconfig import loopback_environ
from ipt.rosmsg import read_mcap_trajectory, time_ns
from ipt.tum import read_tum

RUN_TIMEOUT_S = 900.0
SUMMARY_KEYS = ("final:", ": record:", ": ros2:", "ODOMETRY")


def _flight(video: Path | None, seconds: float, tmp: Path) -> Path:
    if video is not None:
        return video
    out = tmp / "flight"
    subprocess.run(
        [sys.executable, "-m", "ipt.cli", "sim", "--out", str(out), "--seconds", str(seconds)], check=True, timeout=3600
    )
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--video", type=Path, help="folder with frames.mkv and camera.yaml (default: simulate one)")
    p.add_argument("--seconds", type=float, default=4.0, help="length of the simulated flight (default 4)")
    p.add_argument("--realtime", action="store_true", help="pace the recording like a live camera (drops allowed)")
    args = p.parse_args()
    domain = 150 + os.getpid() % 80
    os.environ.update(loopback_environ({}, domain))  # before this process starts DDS

    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from pymavlink import mavutil

    from ipt.receiver.outputs.ros.dds import PoseWithCovarianceStamped

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        flight = _flight(args.video, args.seconds, tmp)
        record = tmp / "flight.mcap"
        participant = DomainParticipant(domain)
        qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(100_000))
        reader = DataReader(participant, Topic(participant, "rt/ipt/pose", PoseWithCovarianceStamped), qos=qos)
        mav = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        mav_port = mav.port.getsockname()[1]
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        udp.bind(("127.0.0.1", 0))
        udp.settimeout(0.02)
        got: list[Any] = []
        odometry: list[Any] = []
        packets = 0
        stop = threading.Event()

        def listen() -> None:
            nonlocal packets
            while not stop.is_set():
                got.extend(s for s in reader.take(500) if isinstance(s, PoseWithCovarianceStamped))
                msg = mav.recv_match(type="ODOMETRY", blocking=True, timeout=0.01)
                if msg is not None:
                    odometry.append(msg)
                with contextlib.suppress(TimeoutError):
                    udp.recv(2048)
                    packets += 1

        thread = threading.Thread(target=listen, daemon=True)
        thread.start()
        run_cmd = [
            "ipt-receiver", "run", "--source", f"video:{flight / 'frames.mkv'}", "--camera",
            str(flight / "camera.yaml"), "--fps", "120", "--send", f"127.0.0.1:{udp.getsockname()[1]}", "--ros2",
            "--record", str(record), "--mavlink", f"udpout:127.0.0.1:{mav_port}",
        ] + (["--realtime"] if args.realtime else [])  # fmt: skip
        started = time.monotonic()
        run = subprocess.run(
            [sys.executable, "-m", "ipt.receiver.cli", *run_cmd[1:]],
            capture_output=True, text=True, timeout=RUN_TIMEOUT_S, env=os.environ.copy(),
        )  # fmt: skip
        run_s = time.monotonic() - started
        time.sleep(0.5)  # what DDS, pymavlink and the kernel still hold
        stop.set()
        thread.join(5.0)
        if run.returncode != 0:
            print(run.stderr, file=sys.stderr)
            return 1
        replay_tum = tmp / "replay.tum"
        replay_cmd = ["ipt-receiver", "replay", "--camera", str(flight / "camera.yaml"), "--video",
                      str(flight / "frames.mkv"), "--fps", "120", "--output", str(replay_tum)]  # fmt: skip
        subprocess.run([sys.executable, "-m", "ipt.receiver.cli", *replay_cmd[1:]], check=True, capture_output=True,
                       timeout=RUN_TIMEOUT_S)  # fmt: skip
        recorded = read_mcap_trajectory(record)
        replayed = read_tum(replay_tum)
        same_count = len(recorded) == len(replayed)
        same_times = same_count and bool(np.all(np.round(recorded.times_s * 1e6) == np.round(replayed.times_s * 1e6)))
        worst_m = float(np.abs(recorded.positions_m - replayed.positions_m).max()) if same_count else None
        stamps = sorted({time_ns(m.header.stamp) for m in got})
        times_us = np.array([o.time_usec for o in odometry], np.int64)
        per_second = max((int(np.sum((times_us >= t) & (times_us < t + 1_000_000))) for t in times_us), default=0)
        finite = sum(1 for o in odometry if np.isfinite([o.vx, o.vy, o.vz]).all())
        participant.__del__()
        mav.close()
        udp.close()
    seconds = float(recorded.times_s[-1] - recorded.times_s[0]) if len(recorded) else 0.0
    result = {
        "command": " ".join(run_cmd),
        "replay_command": " ".join(replay_cmd),
        "cyclonedds_uri": f"loopback only (ipt.receiver.outputs.ros.ddsconfig.LOOPBACK_XML), domain {domain}",
        "run_seconds": round(run_s, 2),
        "udp_packets": packets,
        "record": {
            "poses": len(recorded),
            "replay_poses": len(replayed),
            "same_times": same_times,
            "max_position_difference_m": worst_m,
        },
        "ros2": {
            "received": len(stamps),
            "of_recorded": len(recorded),
            "fraction": round(len(stamps) / len(recorded), 4) if len(recorded) else None,
        },
        "mavlink": {
            "odometry": len(odometry),
            "capture_seconds": round(seconds, 3),
            "max_per_1s_window": per_second,
            "min_interval_ms": round(float(np.diff(times_us).min()) / 1e3, 3) if len(times_us) > 1 else None,
            "with_finite_velocity": finite,
            "finite_velocity_fraction": round(finite / len(odometry), 4) if odometry else None,
        },
        "stderr_summary": [line for line in run.stderr.splitlines() if any(k in line for k in SUMMARY_KEYS)],
    }
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
